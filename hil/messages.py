"""The wire contract as typed, frozen messages (mirrored by the JSON Schemas in ``schemas/``).

Every message carries a per-publisher ``seq`` (so loss is measured, not guessed) and integer
nanosecond stamps named ``*_ns``. ``stamp_ns`` is the time of validity on the message's timeline:
true time for ``Truth``/``CaptureTruth``, rig time for everything else (for a raw sensor message
before synchronisation: its arrival on the rig clock). Positions and velocities are in the local
NED frame of the scenario origin.

Schema evolution: messages evolve only by appending fields with defaults, and a reader ignores
fields it does not know, so an older reader (a recording's replay, a service of the previous
release on the same bus) accepts newer messages. What a field must be is still checked: types,
lengths, ranges (``decode``); an unknown field is simply not read.

Encoding is JSON (msgspec): ``encode(msg)`` and ``decode(Type, payload)``. Decoding validates
types, array lengths and ranges; NaN/inf cannot pass (JSON has no NaN; msgspec writes ``null``,
which a float field rejects).

Every field has one concrete JSON type, so viewers that turn a JSON Schema into typed fields
(Foxglove's and Lichtblick's ``parseJsonSchema``: no ``null``, no unions, no ``$ref``, no map
without ``properties``) decode every type: "absent" is an empty array (``NavSolution.pos_sigma_m``),
a map is an array of ``{key, value}`` (``ServiceStatus.counters``, ``FaultCommand.params``).
``hil.schemas_io.foxglove_schema_problems`` checks it. Messages of the previous form (recordings
made before, where those fields were ``null`` or JSON objects) still decode: ``decode`` falls
back to the legacy form and upgrades it (``LEGACY_FORMS``); ``current_form`` gives a payload's
bytes in the current form, so such recordings rerun bit for bit.
"""

from __future__ import annotations

import re
from collections.abc import Callable, Mapping
from typing import Annotated, Any, TypeVar

import msgspec

Vec3 = Annotated[list[float], msgspec.Meta(min_length=3, max_length=3)]
Quat = Annotated[list[float], msgspec.Meta(min_length=4, max_length=4)]
Seq = Annotated[int, msgspec.Meta(ge=0, le=2**63 - 1)]
Ns = Annotated[int, msgspec.Meta(ge=-(2**62), le=2**62)]
Name = Annotated[str, msgspec.Meta(pattern=r"^[A-Za-z0-9_.\-]{1,64}$")]
#: A 3-vector that may be absent: ``[]`` (absent) or three numbers (checked by the message).
OptVec3 = Annotated[list[float], msgspec.Meta(max_length=3)]


class Count(msgspec.Struct, frozen=True):
    """One entry of a map of integers, as an array element (a JSON Schema viewers can type)."""

    key: str
    value: int


class Rate(msgspec.Struct, frozen=True):
    """One entry of a map of rates (Hz)."""

    key: str
    value: float


class Param(msgspec.Struct, frozen=True):
    """One named parameter (SI units)."""

    key: Name
    value: float


def counts(values: Mapping[str, int]) -> list[Count]:
    """A map of integers as ``[{key, value}, ...]`` in the map's order."""
    return [Count(k, int(v)) for k, v in values.items()]


def rates(values: Mapping[str, float]) -> list[Rate]:
    return [Rate(k, float(v)) for k, v in values.items()]


def params(values: Mapping[str, float]) -> list[Param]:
    return [Param(k, float(v)) for k, v in values.items()]


def _opt_vec3(what: str, v: list[float]) -> None:
    if len(v) not in (0, 3):
        raise ValueError(f"{what} must be [] (absent) or 3 numbers, got {len(v)}")


#: A publisher's own counter (``hil.bus.pubsub.Publisher.next_seq``) is numbered within its
#: process's *restart generation*: ``seq = generation * 2**32 + n``, generation 0 for the first
#: start and N after ``hil up --restart`` restarted the service N times. So a restarted service never
#: reuses a seq, and a reader tells a restart (a new generation, counted from 0 again) from loss (a
#: gap within one generation): ``hil.record.completeness``. Seqs the rig derives from time or a
#: device index (truth, IMU sample, GNSS epoch, PPS second, fusion output) carry no generation: a
#: restart leaves a gap there -- the data nobody delivered while the process was dead.
SEQ_GENERATION_SHIFT = 32
_SEQ_IN_GENERATION = (1 << SEQ_GENERATION_SHIFT) - 1


def generation_seq(generation: int, n: int) -> int:
    """The ``n``-th seq of a publisher counter in restart ``generation``."""
    return (generation << SEQ_GENERATION_SHIFT) | (n & _SEQ_IN_GENERATION)


def seq_generation(seq: int) -> int:
    """The restart generation a seq was published in (0 for derived seqs)."""
    return seq >> SEQ_GENERATION_SHIFT


def seq_in_generation(seq: int) -> int:
    """A seq's number within its generation."""
    return seq & _SEQ_IN_GENERATION


class Message(msgspec.Struct, frozen=True, kw_only=True):
    """Base of every contract message (unknown fields are ignored: see the module docstring)."""

    seq: Seq
    stamp_ns: Ns


class RunInfo(Message, frozen=True, kw_only=True):
    """The run's identity and its time zero, announced by ``world`` at 1 Hz."""

    rig: Name
    start_epoch_ns: int  # wall-clock (CLOCK_REALTIME) instant that is rig time zero
    speed: float  # rig seconds per wall second
    scenario: str
    scenario_sha256: str
    seed: int
    duration_s: float
    origin_lat_deg: float
    origin_lon_deg: float
    origin_alt_m: float
    scenario_toml: Annotated[str, msgspec.Meta(max_length=32768)] = (
        ""  # so every host builds the same scenario
    )
    # the IMU's samples travel as one CAN FD frame each (``--fd``), not four classic ones: the
    # time sync's minimum delay of an IMU timed by arrivals is that frame's wire time
    imu_can_fd: bool = False


class Truth(Message, frozen=True, kw_only=True):
    """True vehicle state at ``stamp_ns`` (true time)."""

    lat_deg: float
    lon_deg: float
    alt_m: float
    pos_ned_m: Vec3
    vel_ned_mps: Vec3
    q_nb: Quat
    f_b_mps2: Vec3
    w_ib_b_radps: Vec3


class ImuSample(Message, frozen=True, kw_only=True):
    """One IMU interval of ``dt_ns`` ending at the capture instant.

    On ``sensor/imu`` both are on the device clock; on ``synced/imu`` time sync has put both on
    the rig clock (``stamp_ns`` re-stamped, ``dt_ns`` the interval with the clock model's rate
    applied), which is what the estimators integrate over."""

    sensor: Name = "imu"
    device_stamp_ns: Ns
    rx_stamp_ns: Ns
    dt_ns: Annotated[int, msgspec.Meta(gt=0, le=10**9)]
    dtheta_b_rad: Vec3
    dvel_b_mps: Vec3
    status: int = 0  # built-in-test flags from the device

    def arrival_ns(self) -> int:
        """When its last frame came in: the IMU's minimum delay includes its frames' wire time."""
        return self.rx_stamp_ns


class GnssFix(Message, frozen=True, kw_only=True):
    """A receiver fix; ``device_stamp_ns`` is its time of validity on the receiver clock.

    Read off a serial line, ``rx_stamp_ns`` is when the read that completed the fix came in and
    ``line_ns`` how long the line had been carrying the fix's epoch by then (its bytes at the
    line's rate, from the first): the receiver's output latency ends ``line_ns`` before
    ``rx_stamp_ns``. 0 for a fix that came on no line."""

    sensor: Name = "gnss"
    device_stamp_ns: Ns
    rx_stamp_ns: Ns
    lat_deg: float
    lon_deg: float
    alt_m: float
    pos_ned_m: Vec3
    vel_ned_mps: Vec3
    pos_sigma_m: Vec3
    vel_sigma_mps: Vec3
    fix_type: Annotated[int, msgspec.Meta(ge=0, le=5)]
    num_sats: Annotated[int, msgspec.Meta(ge=0, le=200)]
    hdop: float
    line_ns: Annotated[int, msgspec.Meta(ge=0, le=10**10)] = 0

    def arrival_ns(self) -> int:
        """When its output began to arrive: what the time sync's minimum delay (the receiver's
        latency) is measured to."""
        return self.rx_stamp_ns - self.line_ns


#: A measurement of any sensor in ``hil.sensor_table`` (raw on ``sensor/<name>``, re-stamped on
#: ``synced/<name>``): every one has ``sensor``, ``seq``, ``stamp_ns``, ``device_stamp_ns`` and
#: ``rx_stamp_ns``, and ``arrival_ns()``: the arrival its sensor's minimum delay is measured to.
Measurement = ImuSample | GnssFix


class CanFrame(Message, frozen=True, kw_only=True):
    """A raw CAN frame as read off the bus; ``stamp_ns`` is the receive stamp on the rig clock."""

    channel: str
    arbitration_id: Annotated[int, msgspec.Meta(ge=0, le=0x1FFFFFFF)]
    is_extended_id: bool = False
    is_fd: bool = False
    bitrate_switch: bool = False
    is_error_frame: bool = False
    data_hex: Annotated[str, msgspec.Meta(pattern=r"^([0-9a-f]{2}){0,64}$")]


class SerialChunk(Message, frozen=True, kw_only=True):
    """Bytes as read off a serial line (a GNSS receiver's UART) in one read; ``stamp_ns`` is the
    receive time on the rig clock. The recording keeps the line byte for byte, so a replay can
    put it back on a line with its spacing (``hil replay --gnss-serial``)."""

    port: Name  # the line's name ("gnss")
    data_hex: Annotated[str, msgspec.Meta(pattern=r"^([0-9a-f]{2}){0,8192}$")]


class TimeTag(Message, frozen=True, kw_only=True):
    """A time-tag edge: device time of the edge and the rig time it was latched at."""

    sensor: Name
    kind: Name  # "sync_frame" | "pps"
    device_stamp_ns: Ns  # the edge on the device clock


class CaptureTruth(Message, frozen=True, kw_only=True):
    """An emulator's true capture time of measurement ``seq`` (same seq as the measurement)."""

    sensor: Name
    true_stamp_ns: Ns


class ClockModel(Message, frozen=True, kw_only=True):
    """The estimated device->rig mapping: rig = device + offset + drift * (device - ref)."""

    sensor: Name
    source: Name  # "timetag" | "arrival" | "passthrough"
    offset_ns: int
    drift_ppb: float
    ref_device_ns: Ns
    residual_rms_ns: float
    n_samples: int
    state: Name  # "converging" | "locked" | "step_recovering"
    steps_detected: int = 0


class NavSolution(Message, frozen=True, kw_only=True):
    """One estimator's solution at rig time ``stamp_ns``.

    ``imu_seq``/``gnss_seq`` name the last synchronised inputs it had consumed, so a recording
    says exactly which inputs each output saw.
    """

    estimator: Name
    pos_ned_m: Vec3
    vel_ned_mps: Vec3
    q_nb: Quat
    lat_deg: float
    lon_deg: float
    alt_m: float
    pos_sigma_m: OptVec3 = []  # 1 sigma N, E, D; [] when the estimator has no covariance
    vel_sigma_mps: OptVec3 = []
    imu_seq: int = -1
    gnss_seq: int = -1
    # 1σ of the attitude error as a rotation about N, E, D (rad): tilt, tilt, heading. A heading
    # σ that says how little the filter knows where heading is unobservable (docs/concepts.md)
    att_sigma_rad: OptVec3 = []  # [] when the estimator has no attitude covariance

    def __post_init__(self) -> None:
        _opt_vec3("pos_sigma_m", self.pos_sigma_m)
        _opt_vec3("vel_sigma_mps", self.vel_sigma_mps)
        _opt_vec3("att_sigma_rad", self.att_sigma_rad)


class FusionJournal(Message, frozen=True, kw_only=True):
    """What the fusion decided over a span of its input: enough to rerun it bit for bit.

    Inputs are consumed in the total order (stamp_ns, source, seq); ``dropped`` lists the inputs
    that were not used, as ``"<why>:<sensor>:<seq>[@<publisher>]"`` (why: ``late`` behind the
    watermark (older than the latency bound), ``order`` an IMU sample at the stamp of another one
    the output predictor holds, ``dup``, ``future``, ``implausible``, ``inbox`` dropped by the service's
    bounded inbox, ``overflow`` evicted from the reorder buffer, ``prealign`` valid before a restarted
    fusion's re-alignment; the publisher is the Zenoh source id, absent offline). ``gated`` lists
    the GNSS fixes the integrity gate kept from estimators, as ``"<sensor>:<seq>[@<publisher>]"``
    (from all) or ``"...>estimator"`` (from that one): not needed to rerun (the gate is
    deterministic), but the record of what was refused and why. A span with many decisions is
    published as several journals.
    """

    watermark_ns: Ns
    consumed: int
    dropped: list[str] = []
    gated: list[str] = []
    # IMU samples the fusion's horizon took but its output predictor did not (they arrived behind
    # a newer one), as ``"imu:<seq>[@<publisher>]"``: rerun replays them the same way
    unpredicted: list[str] = []


class ServiceStatus(Message, frozen=True, kw_only=True):
    """A service's health, published at 1 Hz."""

    service: Name
    state: Name  # "starting" | "running" | "degraded" | "stopping"
    pid: int
    uptime_s: float
    rates_hz: list[Rate] = []
    counters: list[Count] = []
    last_error: str = ""

    def counter_map(self) -> dict[str, int]:
        return {c.key: c.value for c in self.counters}

    def rate_map(self) -> dict[str, float]:
        return {r.key: r.value for r in self.rates_hz}


class Event(Message, frozen=True, kw_only=True):
    """Something that happened: a fault injected, a service restarted, a recording gap."""

    kind: Name
    source: Name
    detail: str = ""


class EstimatorHealth(Message, frozen=True, kw_only=True):
    """One estimator's health at rig time ``stamp_ns``, as real numbers (innovation test ratios,
    NIS, gains, bias norms, counts), published by the fusion at 1 Hz of rig time on
    ``health/<estimator>`` -- in the manner of PX4's ``estimator_innovation_test_ratios``.

    ``names[i]`` names ``values[i]`` (parallel lists rather than a map: viewers such as Foxglove
    plot ``values[i]`` and cannot read a JSON map with no declared properties); which names an
    estimator reports is documented with it (``docs/estimators.md``).
    """

    estimator: Name
    names: Annotated[list[Name], msgspec.Meta(max_length=64)] = []
    values: Annotated[list[float], msgspec.Meta(max_length=64)] = []

    def __post_init__(self) -> None:
        if len(self.names) != len(self.values):
            raise ValueError(f"{len(self.names)} names for {len(self.values)} values")

    def as_dict(self) -> dict[str, float]:
        return dict(zip(self.names, self.values, strict=True))


class FusionSettings(Message, frozen=True, kw_only=True):
    """The fusion's configuration, published once at its start on ``fusion/config``: what
    ``hil rerun`` needs to build the same core (``hil.fusion.core.FusionConfig``, field for field)."""

    estimators: Annotated[list[Name], msgspec.Meta(max_length=64)]
    lag_ns: Annotated[int, msgspec.Meta(ge=0, le=60 * 10**9)]
    output_every: Annotated[int, msgspec.Meta(ge=1, le=10**6)]
    max_future_ns: int
    max_buffered: int
    max_dtheta_rad: float
    max_dvel_mps: float
    max_pos_m: float
    max_vel_mps: float
    gap_confirm_inputs: int
    # the seed estimators run in feedback form, and ekf15's calibration states ("", "gyro",
    # "gyro+accel"); absent in recordings made before them: open loop, 15 states
    feedback: Annotated[list[Name], msgspec.Meta(max_length=64)] = []
    ekf_calibration: Annotated[str, msgspec.Meta(max_length=16)] = ""
    # added with the GNSS integrity gate; their defaults are a recording from before it (no gate)
    max_buffered_aiding: int = 0
    gnss_gate_chi2: float = 0.0
    gnss_alarm_after_ns: int = 0
    gnss_reacquire_after_ns: int = 0
    gnss_gate_reference: str = ""
    gnss_sigma_floor: bool = False
    gnss_min_interval: float = 0.0
    # the output predictor (hil.fusion.predictor); absent in recordings made before it, which
    # published the horizon's state lag_ns late
    output_predictor: bool = False
    # the compensation filters' coast through a GNSS gap (hil.estimators.compensation); absent in
    # recordings made before it, whose filters continued the last difference
    gnss_coast: bool = False
    # how ekf15 and the feedback INS are told the IMU's bias wander (hil.estimators.tuning);
    # absent in recordings made before it, which told them the instability B and the gyro's τ
    imu_bias_model: Annotated[str, msgspec.Meta(max_length=32)] = "instability"
    # a fix the GNSS gate reacquires re-initialises the estimators that can, and a flagged IMU
    # sample reacquires at once (hil.fusion.gnss_gate's rule 4); absent in recordings made
    # before it, whose gate let one fix through
    gnss_reset: bool = False
    # that reset at a flagged IMU sample only while GNSS is trusted (not while its fixes are being
    # rejected: a spoof); absent in recordings made before it, whose reset took any fix
    gnss_reset_needs_trust: bool = False
    # that reset re-initialises the free INS too, and the open-loop filters that correct it start
    # again on the fix; absent in recordings made before it, whose free INS kept the fault's error
    gnss_reset_free_ins: bool = False
    # that reset levels the tilt against the GNSS velocity's rate (a turn's acceleration) and the
    # free INS's on the mean of its recent clean samples; absent in recordings made before it,
    # levelled on a = 0 and the free INS on its last sample
    gnss_reset_accel: bool = False
    # the reset's fix after an IMU fault continues the GNSS track before the fault, or it is held
    # out as rejected; absent in recordings made before it, whose reset took the first fix after
    gnss_reset_checks_track: bool = False


class FaultCommand(Message, frozen=True, kw_only=True):
    """A fault to inject now, sent on ``hil/<rig>/control/fault`` (``hil fault``).

    ``kind`` names the fault (``hil.faults.FAULT_KINDS``: which service applies it and which
    ``params`` it takes, SI units); ``target`` a service (``kill_service``) or a sensor
    (``clock_step``); ``duration_s`` 0 means until the end of the run (or instantaneous). The
    service that applies it publishes a ``fault_start`` ``Event`` (and ``fault_end``), so the
    recording holds both the command and its effect.
    """

    kind: Name
    target: Annotated[str, msgspec.Meta(pattern=r"^[A-Za-z0-9_.\-]{0,64}$")] = ""
    params: Annotated[list[Param], msgspec.Meta(max_length=16)] = []
    duration_s: Annotated[float, msgspec.Meta(ge=0.0, le=1e6)] = 0.0

    def param_map(self) -> dict[str, float]:
        return {p.key: p.value for p in self.params}


CONTRACT_TYPES: tuple[type[Message], ...] = (
    RunInfo,
    Truth,
    ImuSample,
    GnssFix,
    CanFrame,
    TimeTag,
    CaptureTruth,
    ClockModel,
    NavSolution,
    FusionJournal,
    ServiceStatus,
    Event,
    FaultCommand,
    EstimatorHealth,
    FusionSettings,
    SerialChunk,
)
TYPES_BY_NAME: dict[str, type[Message]] = {f"hil.{t.__name__}": t for t in CONTRACT_TYPES}

M = TypeVar("M", bound=Message)


# -- the previous form of the types whose JSON changed (recordings made before still decode) --


class _NavSolutionV0(NavSolution, frozen=True, kw_only=True):
    """``pos_sigma_m``/``vel_sigma_mps`` were ``null`` when absent."""

    pos_sigma_m: Vec3 | None = None  # type: ignore[assignment]
    vel_sigma_mps: Vec3 | None = None  # type: ignore[assignment]

    def __post_init__(self) -> None:
        pass


class _ServiceStatusV0(ServiceStatus, frozen=True, kw_only=True):
    """``rates_hz``/``counters`` were JSON objects (either may come in either form here)."""

    rates_hz: dict[str, float] | list[Rate] = {}  # type: ignore[assignment]
    counters: dict[str, int] | list[Count] = {}  # type: ignore[assignment]


class _FaultCommandV0(FaultCommand, frozen=True, kw_only=True):
    """``params`` was a JSON object."""

    params: Annotated[dict[Name, float], msgspec.Meta(max_length=16)] = {}  # type: ignore[assignment]


def _fields(m: msgspec.Struct) -> dict[str, Any]:
    return {f: getattr(m, f) for f in m.__struct_fields__}


def _nav_v0(m: Any) -> NavSolution:
    return NavSolution(
        **{
            **_fields(m),
            "pos_sigma_m": m.pos_sigma_m or [],
            "vel_sigma_mps": m.vel_sigma_mps or [],
        }
    )


def _status_v0(m: Any) -> ServiceStatus:
    r, c = m.rates_hz, m.counters
    return ServiceStatus(
        **{
            **_fields(m),
            "rates_hz": rates(r) if isinstance(r, dict) else r,
            "counters": counts(c) if isinstance(c, dict) else c,
        }
    )


def _fault_v0(m: Any) -> FaultCommand:
    return FaultCommand(**{**_fields(m), "params": params(m.params)})


#: type -> (its previous form, the upgrade to the current one)
LEGACY_FORMS: dict[type[Message], tuple[type[Message], Callable[[Any], Message]]] = {
    NavSolution: (_NavSolutionV0, _nav_v0),
    ServiceStatus: (_ServiceStatusV0, _status_v0),
    FaultCommand: (_FaultCommandV0, _fault_v0),
}

_encoder = msgspec.json.Encoder()
_decoders: dict[type[Any], msgspec.json.Decoder[Any]] = {}


_KEY_NAME = re.compile(r"^[A-Za-z0-9_\-]{1,64}$")


def check_name(what: str, name: str) -> str:
    """Reject names that would break key expressions (``*``, ``/``, ``$``, empty): a rig, a
    service, an estimator (``nav/<name>``). ``hil.bus.keys`` and the layers below it check alike."""
    if not isinstance(name, str) or not _KEY_NAME.match(name):
        raise ValueError(f"{what} {name!r} is not a valid name: use 1-64 of [A-Za-z0-9_-]")
    return name


def encode(msg: Message) -> bytes:
    """JSON bytes of a message."""
    return _encoder.encode(msg)


#: the most messages one batch payload may carry (``split_batch``): one CAN sample's frames are
#: 1-5, a drained read a few samples'; more is an attack or a bug
MAX_BATCH = 64
_raw_list = msgspec.json.Decoder(list[msgspec.Raw])


def encode_batch(msgs: list[Message]) -> bytes:
    """Several messages of one key as one payload: a JSON array of them, each element the bytes
    ``encode`` gives (``hil.bus.pubsub.Publisher.put_many``)."""
    return b"[" + b",".join([_encoder.encode(m) for m in msgs]) + b"]"


def split_batch(payload: bytes) -> list[bytes]:
    """The message payloads in a sample's payload: itself, or the elements of a batch (a JSON
    array, ``encode_batch``) as the bytes they were sent as. Raises ``ValueError`` on a batch
    that is not a JSON array, is empty, or holds more than ``MAX_BATCH`` messages; each element
    is then decoded and validated as a message on its own."""
    if payload[:1] != b"[":
        return [payload]
    try:
        items = _raw_list.decode(payload)
    except msgspec.DecodeError as err:  # ValidationError too
        raise ValueError(f"not a batch of messages: {err}") from None
    except RecursionError:  # msgspec's answer to ``[[[[...``: as malformed as any other
        raise ValueError("not a batch of messages: JSON nested too deeply") from None
    if not 0 < len(items) <= MAX_BATCH:
        raise ValueError(f"a batch of {len(items)} messages (1 to {MAX_BATCH} allowed)")
    return [bytes(r) for r in items]


class _SeqOnly(msgspec.Struct):
    seq: int


_seq_only = msgspec.json.Decoder(_SeqOnly)


def payload_seq(payload: bytes | bytearray | memoryview) -> int:
    """An encoded message's ``seq``, the rest left unparsed (~1 us); raises
    ``msgspec.ValidationError``/``DecodeError`` if it has none."""
    return _seq_only.decode(payload).seq


def _decoder(cls: type[Any]) -> msgspec.json.Decoder[Any]:
    dec = _decoders.get(cls)
    if dec is None:
        dec = _decoders[cls] = msgspec.json.Decoder(cls)
    return dec


def decode(cls: type[M], payload: bytes | bytearray | memoryview) -> M:
    """Decode and validate; raises ``msgspec.ValidationError``/``DecodeError`` on bad input.

    A payload in the previous form of its type (``LEGACY_FORMS``) is accepted and upgraded.
    """
    try:
        return _decoder(cls).decode(payload)
    except RecursionError:  # msgspec skipping an unknown field nested ~10^5 deep: malformed input
        raise msgspec.DecodeError(f"not a valid {cls.__name__}: JSON nested too deeply") from None
    except msgspec.ValidationError as err:
        legacy = LEGACY_FORMS.get(cls)
        if legacy is None:
            raise
        try:
            old = _decoder(legacy[0]).decode(payload)
        except msgspec.ValidationError:
            raise err from None
        return legacy[1](old)  # type: ignore[return-value]


def current_form(cls: type[Message], payload: bytes) -> bytes:
    """``payload`` as the current encoder writes it: unchanged unless it is in a legacy form."""
    try:
        _decoder(cls).decode(payload)
        return payload
    except (msgspec.ValidationError, msgspec.DecodeError):
        if cls not in LEGACY_FORMS:
            return payload
    try:
        return encode(decode(cls, payload))
    except (msgspec.ValidationError, msgspec.DecodeError):
        return payload


def encoded_today(cls: type[Message], payload: bytes) -> bytes:
    """``payload`` decoded -- a legacy form upgraded, fields appended since its recording given
    their defaults -- and encoded again: the bytes today's encoder writes for the same values (the
    payload itself if it does not decode). What a rerun compares a recorded output by where its
    bytes differ from the recomputed one's; ``current_form`` leaves a payload of the current form
    as it is (it runs on every message of an export)."""
    try:
        return encode(decode(cls, payload))
    except (msgspec.ValidationError, msgspec.DecodeError):
        return payload


def schema_name(cls: type[Message]) -> str:
    """The MCAP schema name of a type: ``hil.<Type>``."""
    return f"hil.{cls.__name__}"


def _inline(node: Any, defs: dict[str, Any]) -> Any:
    """Replace every ``$ref`` into ``$defs`` by the definition itself (viewers do not follow refs)."""
    if isinstance(node, dict):
        ref = node.get("$ref")
        if isinstance(ref, str) and ref.startswith("#/$defs/"):
            rest = {k: v for k, v in node.items() if k != "$ref"}
            return _inline({**defs[ref.removeprefix("#/$defs/")], **rest}, defs)
        return {k: _inline(v, defs) for k, v in node.items()}
    if isinstance(node, list):
        return [_inline(v, defs) for v in node]
    return node


def json_schema(cls: type[Message]) -> dict[str, Any]:
    """The JSON Schema of a type, self-contained (no ``$ref``), with ``hil.<Type>`` as its title."""
    raw = msgspec.json.schema(cls)
    defs = raw.get("$defs", {})
    body = _inline(dict(defs[cls.__name__]), defs)
    body["title"] = schema_name(cls)
    out: dict[str, Any] = {"$schema": "https://json-schema.org/draft/2020-12/schema", "$id": schema_name(cls)}
    out.update(body)
    return out
