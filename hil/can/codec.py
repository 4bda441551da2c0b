"""The IMU's CAN codec, built at start-up from ``schemas/imu.dbc`` (the single source of truth).

Nothing about the frame layout is typed here: identifiers, lengths, bit positions, scale
factors, which frames make up a sample (the ``HilRole`` message attribute) and how many bytes the
E2E CRC covers (``HilE2EDataLength``) are all read from the DBC with cantools. From those the
codec precompiles shift/mask tables, because cantools' generic ``decode_message`` (a few µs per
frame) is the wrong tool for a 2 kHz, four-frames-per-sample stream; the unit tests prove the fast
path bit-identical to cantools' own encoder and decoder for every frame.

What the wire does to the signal (see docs/can-protocol.md): every delta is rounded to the
nearest multiple of its DBC scale (error uniform in ±q/2, RMS q/√12, white: it does not
accumulate as a bias), saturates at full scale with a per-axis flag, and the device time travels
as unsigned ns modulo 2^48 (the assembler unwraps it).

Error tree::

    ValueError
     ├── CodecError    the DBC cannot serve as the IMU protocol (says which message/signal)
     └── EncodeError   a value cannot be put on the wire (NaN/inf, negative time ...)
"""

from __future__ import annotations

import math
import os
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

import can

from hil.can.e2e import COUNTER_MODULO, counter_delta, next_counter, p01_crc

if TYPE_CHECKING:
    # cantools (~0.1 s of CPU at import) reads the DBC once, in from_dbc: after the service
    # said it is ready (the node is built on the run's announcement, before time zero)
    import cantools

DEVICE_TIME_BITS = 48
DEVICE_TIME_MODULO = 1 << DEVICE_TIME_BITS

# StatusWord bits (documented in the DBC comment of IMU_Status).
GYRO_FAULT = 1 << 0
ACCEL_FAULT = 1 << 1
GYRO_SATURATED = 1 << 2
ACCEL_SATURATED = 1 << 3
OVER_TEMPERATURE = 1 << 4
CLOCK_UNSYNCED = 1 << 5
BIT_RUNNING = 1 << 6
BIT_FAILED = 1 << 7

_AXES = ("X", "Y", "Z")
_SAMPLE_SIGNALS = frozenset(
    [f"DeltaAngle{a}" for a in _AXES] + [f"DeltaVel{a}" for a in _AXES] + ["DeviceTime"]
)
ROLES = ("sync", "sample_part", "sample_fd", "status")


class CodecError(ValueError):
    """The DBC is unusable as the IMU protocol; the message names the frame and the rule."""


class EncodeError(ValueError):
    """A value cannot be encoded (not finite, out of the representable domain)."""


def default_dbc_path() -> Path:
    """``$HIL_DBC`` if set, else the repository's ``schemas/imu.dbc`` (next to the package)."""
    env = os.environ.get("HIL_DBC")
    if env:
        return Path(env)
    return Path(__file__).resolve().parents[2] / "schemas" / "imu.dbc"


@dataclass(frozen=True, slots=True)
class SignalField:
    """One little-endian DBC signal as shift/mask arithmetic."""

    name: str
    start: int
    length: int
    signed: bool
    scale: float
    offset: float
    is_integer: bool  # scale 1, offset 0: decoded as int (times, flags, words)

    @property
    def mask(self) -> int:
        return (1 << self.length) - 1

    @property
    def raw_min(self) -> int:
        return -(1 << (self.length - 1)) if self.signed else 0

    @property
    def raw_max(self) -> int:
        return (1 << (self.length - 1)) - 1 if self.signed else (1 << self.length) - 1

    def extract(self, word: int) -> int:
        raw = (word >> self.start) & self.mask
        if self.signed and raw >> (self.length - 1):
            raw -= 1 << self.length
        return raw

    def value(self, raw: int) -> float | int:
        return raw if self.is_integer else raw * self.scale + self.offset


@dataclass(slots=True)
class FrameLayout:
    """One DBC message: identity, role, E2E extent and its data signals."""

    frame_id: int
    name: str
    length: int
    is_fd: bool
    brs: bool
    role: str
    e2e_length: int
    fields: list[SignalField]
    counter_start: int = 8
    crc_byte: int = 0
    by_name: dict[str, SignalField] = field(default_factory=dict)

    # word (the frame as a little-endian int) -> {signal: value}, CRC/counter excluded
    decode_word: Callable[[int], dict[str, float | int]] = field(init=False, repr=False)

    def __post_init__(self) -> None:
        self.decode_word = _compile_decoder(self.name, self.fields)


def _compile_decoder(name: str, fields: list[SignalField]) -> Any:
    """Generate ``word -> {signal: value}`` for one frame as straight-line Python.

    The bridge decodes every frame at up to 8 kHz; a loop over field objects with method calls
    costs several µs per frame, the generated expression a fraction of that. The source holds
    only numbers parsed by cantools and signal names as ``repr`` string literals.
    """
    items = []
    for f in fields:
        raw = f"((word >> {f.start}) & {f.mask:#x})"
        if f.signed:
            sign = 1 << (f.length - 1)
            raw = f"(({raw} ^ {sign:#x}) - {sign:#x})"
        if not f.is_integer:
            raw = f"{raw} * {f.scale!r}" + (f" + {f.offset!r}" if f.offset else "")
        items.append(f"{f.name!r}: {raw}")
    src = "def decode_word(word):\n    return {" + ", ".join(items) + "}\n"
    scope: dict[str, Any] = {}
    exec(compile(src, f"<dbc:{name}>", "exec"), scope)
    return scope["decode_word"]


def _attr(msg: cantools.database.can.Message, name: str, default: object) -> object:
    attrs = msg.dbc.attributes if msg.dbc is not None else {}
    return attrs[name].value if name in attrs else default


def _layout(msg: cantools.database.can.Message) -> FrameLayout:
    role = str(_attr(msg, "HilRole", ""))
    if role not in ROLES:
        raise CodecError(f"{msg.name}: HilRole {role!r} is not one of {ROLES}")
    if msg.is_extended_frame:
        raise CodecError(f"{msg.name}: extended identifiers are not used by the IMU protocol")
    e2e_len = int(_attr(msg, "HilE2EDataLength", msg.length))  # type: ignore[call-overload]
    if not 2 <= e2e_len <= msg.length:
        raise CodecError(f"{msg.name}: HilE2EDataLength {e2e_len} outside 2..{msg.length}")
    fields: list[SignalField] = []
    crc_ok = ctr_ok = False
    for sig in msg.signals:
        if sig.byte_order != "little_endian":
            raise CodecError(f"{msg.name}.{sig.name}: only little-endian signals are supported")
        if sig.name.endswith("_CRC"):
            if (sig.start, sig.length) != (0, 8):
                raise CodecError(f"{msg.name}.{sig.name}: the E2E CRC must be bits 0..7")
            crc_ok = True
            continue
        if sig.name.endswith("_Counter"):
            if (sig.start, sig.length) != (8, 4):
                raise CodecError(f"{msg.name}.{sig.name}: the E2E counter must be bits 8..11")
            ctr_ok = True
            continue
        if sig.start + sig.length > e2e_len * 8:
            raise CodecError(f"{msg.name}.{sig.name}: outside the E2E-protected {e2e_len} bytes")
        scale, offset = float(sig.scale), float(sig.offset)
        fields.append(
            SignalField(
                name=sig.name,
                start=sig.start,
                length=sig.length,
                signed=sig.is_signed,
                scale=scale,
                offset=offset,
                is_integer=scale == 1.0 and offset == 0.0,
            )
        )
    if not (crc_ok and ctr_ok):
        raise CodecError(f"{msg.name}: needs an <x>_CRC (bits 0..7) and an <x>_Counter (bits 8..11) signal")
    brs = bool(int(str(_attr(msg, "CANFD_BRS", "1")))) if msg.is_fd else False
    return FrameLayout(
        frame_id=msg.frame_id,
        name=msg.name,
        length=msg.length,
        is_fd=bool(msg.is_fd),
        brs=brs,
        role=role,
        e2e_length=e2e_len,
        fields=fields,
        by_name={f.name: f for f in fields},
    )


class ImuCanCodec:
    """Encodes IMU samples into CAN frames (keeping the per-identifier rolling counters).

    ``fd=False``: each sample is the ``sample_part`` frames (classic CAN, 8 bytes each), the one
    holding ``DeviceTime`` sent last. ``fd=True``: each sample is the single ``sample_fd`` frame.
    The ``status`` frame precedes a sample whose status changed and every ``status_every``-th one.
    """

    def __init__(
        self, db: cantools.database.Database, *, fd: bool = False, source: str = "", status_every: int = 40
    ):
        self.db = db
        self.fd = fd
        self.source = source
        self.status_every = max(1, int(status_every))
        self.layouts: dict[int, FrameLayout] = {}
        for msg in db.messages:
            lay = _layout(msg)
            self.layouts[lay.frame_id] = lay
        by_role: dict[str, list[FrameLayout]] = {r: [] for r in ROLES}
        for lay in self.layouts.values():
            by_role[lay.role].append(lay)
        for role in ("sync", "status", "sample_fd"):
            if len(by_role[role]) != 1:
                raise CodecError(f"the DBC needs exactly one {role!r} frame, found {len(by_role[role])}")
        self.sync_layout = by_role["sync"][0]
        self.status_layout = by_role["status"][0]
        self.fd_layout = by_role["sample_fd"][0]
        # The part carrying DeviceTime goes last: its arrival completes the sample.
        self.part_layouts = sorted(
            by_role["sample_part"], key=lambda lay: ("DeviceTime" in lay.by_name, lay.frame_id)
        )
        part_names = [f.name for lay in self.part_layouts for f in lay.fields]
        if not set(part_names) >= _SAMPLE_SIGNALS or len(part_names) != len(set(part_names)):
            raise CodecError(f"sample_part frames must carry each of {sorted(_SAMPLE_SIGNALS)} once")
        if not set(self.fd_layout.by_name) >= _SAMPLE_SIGNALS:
            raise CodecError(f"{self.fd_layout.name} must carry {sorted(_SAMPLE_SIGNALS)}")
        if not self.fd_layout.is_fd:
            raise CodecError(f"{self.fd_layout.name}: a sample_fd frame must be CAN FD (VFrameFormat)")
        for need, lay in (("DeviceTime", self.sync_layout), ("StatusWord", self.status_layout)):
            if need not in lay.by_name:
                raise CodecError(f"{lay.name} must carry {need}")
        self.sample_layouts: list[FrameLayout] = [self.fd_layout] if fd else self.part_layouts
        ref = self.fd_layout.by_name
        self.dtheta_lsb_rad = ref["DeltaAngleX"].scale
        self.dvel_lsb_mps = ref["DeltaVelX"].scale
        self.dtheta_max_rad = ref["DeltaAngleX"].raw_max * self.dtheta_lsb_rad
        self.dvel_max_mps = ref["DeltaVelX"].raw_max * self.dvel_lsb_mps
        self._tx_counter: dict[int, int] = dict.fromkeys(self.layouts, 0)
        self._last_status: int | None = None
        self.samples_encoded = 0
        self.saturated_samples = 0

    # -- construction --------------------------------------------------------------------
    @classmethod
    def from_dbc(cls, path: str | os.PathLike[str] | None = None, *, fd: bool = False) -> ImuCanCodec:
        """Load the DBC (default :func:`default_dbc_path`) and compile the codec from it."""
        import cantools

        p = Path(path) if path is not None else default_dbc_path()
        try:
            db = cantools.database.load_file(str(p), database_format="dbc")
        except FileNotFoundError as err:
            raise CodecError(f"DBC {str(p)!r} not found (set HIL_DBC or pass a path)") from err
        except Exception as err:  # cantools raises several parse error types
            raise CodecError(f"DBC {str(p)!r} does not parse: {err}") from err
        return cls(db, fd=fd, source=str(p))

    @property
    def frame_ids(self) -> frozenset[int]:
        return frozenset(self.layouts)

    # -- encoding ------------------------------------------------------------------------
    def _frame(self, lay: FrameLayout, raws: dict[str, int], counter: int | None = None) -> can.Message:
        """One frame; the identifier's rolling counter advances unless ``counter`` is given."""
        if counter is None:
            ctr = self._tx_counter[lay.frame_id]
            self._tx_counter[lay.frame_id] = next_counter(ctr)
        else:
            ctr = counter
        word = ctr << lay.counter_start
        for f in lay.fields:
            word |= (raws.get(f.name, 0) & f.mask) << f.start
        data = bytearray(word.to_bytes(lay.length, "little"))
        data[lay.crc_byte] = p01_crc(lay.frame_id, data, lay.e2e_length, lay.crc_byte)
        return can.Message(
            arbitration_id=lay.frame_id,
            is_extended_id=False,
            is_fd=lay.is_fd,
            bitrate_switch=lay.brs,
            data=data,
            dlc=lay.length,
        )

    @staticmethod
    def _time_raw(device_stamp_ns: int) -> int:
        if not isinstance(device_stamp_ns, int) or isinstance(device_stamp_ns, bool):
            raise EncodeError(f"device_stamp_ns must be an int, got {type(device_stamp_ns).__name__}")
        return device_stamp_ns % DEVICE_TIME_MODULO

    @staticmethod
    def _quantise(value: float, lsb: float, raw_max: int, what: str) -> tuple[int, bool]:
        """Round to the nearest LSB (half to even) and saturate symmetrically at full scale."""
        if not math.isfinite(value):
            raise EncodeError(f"{what}={value!r} is not finite")
        raw = round(value / lsb)
        if raw > raw_max:
            return raw_max, True
        if raw < -raw_max:  # symmetric: -full scale, so a saturated sign never flips meaning
            return -raw_max, True
        return raw, False

    def encode_status(self, status: int) -> can.Message:
        """The status/BIT frame now (the codec also emits it by itself from ``encode_sample``)."""
        if not 0 <= int(status) <= 0xFFFF:
            raise EncodeError(f"status {status} does not fit the 16-bit StatusWord")
        self._last_status = int(status)
        return self._frame(
            self.status_layout,
            {"StatusWord": int(status), "SampleCount": self.samples_encoded & 0xFFFFFFFF},
        )

    def encode_sample(
        self,
        *,
        device_stamp_ns: int,
        dtheta_b_rad: Sequence[float],
        dvel_b_mps: Sequence[float],
        status: int = 0,
    ) -> list[can.Message]:
        """Frames of one sample, in transmission order (status frame first when due).

        Raises ``EncodeError`` (nothing is consumed: counters unchanged) on NaN/inf, wrong vector
        length or a status that does not fit 16 bits.
        """
        if len(dtheta_b_rad) != 3 or len(dvel_b_mps) != 3:
            raise EncodeError("dtheta_b_rad and dvel_b_mps must have 3 components")
        if not 0 <= int(status) <= 0xFFFF:
            raise EncodeError(f"status {status} does not fit the 16-bit StatusWord")
        raws: dict[str, int] = {"DeviceTime": self._time_raw(device_stamp_ns), "StatusWord": int(status)}
        sat_any = False
        for i, axis in enumerate(_AXES):
            r, s = self._quantise(float(dtheta_b_rad[i]), self.dtheta_lsb_rad, self._raw_max_angle, "dtheta")
            raws[f"DeltaAngle{axis}"] = r
            raws[f"GyroSat{axis}"] = int(s)
            sat_any |= s
            r, s = self._quantise(float(dvel_b_mps[i]), self.dvel_lsb_mps, self._raw_max_vel, "dvel")
            raws[f"DeltaVel{axis}"] = r
            raws[f"AccelSat{axis}"] = int(s)
            sat_any |= s
        out: list[can.Message] = []
        if self._last_status != int(status) or self.samples_encoded % self.status_every == 0:
            out.append(self.encode_status(int(status)))
        out.extend(self._frame(lay, raws) for lay in self.sample_layouts)
        self.samples_encoded += 1
        self.saturated_samples += int(sat_any)
        return out

    @property
    def _raw_max_angle(self) -> int:
        return self.fd_layout.by_name["DeltaAngleX"].raw_max

    @property
    def _raw_max_vel(self) -> int:
        return self.fd_layout.by_name["DeltaVelX"].raw_max

    def encode_sync(self, device_stamp_ns: int) -> can.Message:
        """The time-tag frame for a sync edge at ``device_stamp_ns`` on the device clock."""
        return self._frame(self.sync_layout, {"DeviceTime": self._time_raw(device_stamp_ns)})

    def restamp_sync(self, frame: can.Message, device_stamp_ns: int) -> can.Message:
        """``frame`` (a sync frame this codec encoded) stating ``device_stamp_ns`` instead: the same
        rolling counter (it is the same transmission, only its time changed), a new E2E CRC, no
        codec state touched -- so it may be called from another thread than the encoder's."""
        if frame.arbitration_id != self.sync_layout.frame_id:
            raise EncodeError(f"0x{frame.arbitration_id:X} is not the sync frame")
        counter = frame.data[1] & 0x0F  # bits 8..11, as the DBC check pins them
        return self._frame(self.sync_layout, {"DeviceTime": self._time_raw(device_stamp_ns)}, counter)

    # -- decoding (no checks: the assembler does those) ----------------------------------
    def decode(self, frame_id: int, data: bytes | bytearray) -> dict[str, float | int]:
        """Data signals of a known frame, like cantools' ``decode_message`` minus CRC/counter."""
        lay = self.layouts[frame_id]
        return lay.decode_word(int.from_bytes(data, "little"))


@dataclass(frozen=True, slots=True)
class DecodedSample:
    """One reassembled IMU sample. ``rx_timestamp_s``: python-can stamp of the completing frame."""

    device_stamp_ns: int
    dtheta_b_rad: tuple[float, float, float]
    dvel_b_mps: tuple[float, float, float]
    status: int
    rx_timestamp_s: float


@dataclass(frozen=True, slots=True)
class DecodedSync:
    """A sync (time-tag) frame: the edge on the device clock and the frame's receive stamp."""

    device_stamp_ns: int
    rx_timestamp_s: float


class DeviceTimeUnwrapper:
    """Turns the wire's 48-bit device time back into a monotone int (nearest-epoch rule)."""

    def __init__(self) -> None:
        self._epoch = 0
        self._last: int | None = None

    def __call__(self, raw: int) -> int:
        half = DEVICE_TIME_MODULO >> 1
        if self._last is None:
            self._last = raw
            return raw
        diff = raw - self._last
        if diff < -half:  # wrapped forward
            self._epoch += DEVICE_TIME_MODULO
            self._last = raw
        elif diff > half:  # a straggler from before the wrap
            return self._epoch - DEVICE_TIME_MODULO + raw
        else:
            self._last = raw
        return self._epoch + raw


COUNTER_NAMES = (
    "frames",
    "unknown_id",
    "bad_dlc",
    "bad_crc",
    "bad_counter",
    "counter_jump",
    "lost_frames",
    "repeated",
    "incomplete_sample",
    "error_frame",
    "remote_frame",
    "samples",
    "syncs",
    "status",
    "saturated",
)


class ImuFrameAssembler:
    """Pure state machine: frames in, decoded samples/syncs out. No I/O, no clock.

    Checks, in order: frame kind (error/remote), identifier, length, counter value (15 is
    invalid), E2E CRC, then counter continuity per identifier (repeat -> dropped; a gap ->
    ``counter_jump`` and ``lost_frames``, frame kept). Classic parts are grouped by their shared
    counter value; a group left unfinished when the next counter value starts is dropped as
    ``incomplete_sample``. Both classic and FD samples are accepted whatever the codec's mode, so a
    bridge need not know the sender's configuration.
    """

    def __init__(self, codec: ImuCanCodec) -> None:
        self.codec = codec
        self.counters: dict[str, int] = dict.fromkeys(COUNTER_NAMES, 0)
        self._layouts = codec.layouts
        self._last_ctr: dict[int, int] = {}
        self._n_parts = len(codec.part_layouts)
        self._part_ids = frozenset(lay.frame_id for lay in codec.part_layouts)
        self._group: dict[int, FrameLayout | int] = {}
        self._group_words: dict[int, int] = {}
        self._group_ctr = -1
        self._status = 0
        self.last_sample_count: int | None = None
        self._unwrap = DeviceTimeUnwrapper()
        self._sync_unwrap = DeviceTimeUnwrapper()
        # Every rejected frame or detected gap bumps ``problems`` and says what it was, so a
        # caller can surface it (status last_error) by comparing one int per frame.
        self.problems = 0
        self.last_problem: tuple[str, str] = ("", "")

    def _problem(self, kind: str, msg: can.Message, detail: str) -> None:
        self.counters[kind] += 1
        self.problems += 1
        self.last_problem = (
            kind,
            f"CAN 0x{msg.arbitration_id:X} [{len(msg.data)}] {msg.data.hex()}: {detail}",
        )

    def _sample(self, values: dict[str, float | int], status: int, rx: float) -> DecodedSample:
        g = (values["GyroSatX"], values["GyroSatY"], values["GyroSatZ"])
        a = (values["AccelSatX"], values["AccelSatY"], values["AccelSatZ"])
        if any(g) or any(a):
            self.counters["saturated"] += 1
            status |= (GYRO_SATURATED if any(g) else 0) | (ACCEL_SATURATED if any(a) else 0)
        self.counters["samples"] += 1
        v = values
        return DecodedSample(
            device_stamp_ns=self._unwrap(int(v["DeviceTime"])),
            dtheta_b_rad=(float(v["DeltaAngleX"]), float(v["DeltaAngleY"]), float(v["DeltaAngleZ"])),
            dvel_b_mps=(float(v["DeltaVelX"]), float(v["DeltaVelY"]), float(v["DeltaVelZ"])),
            status=int(status),
            rx_timestamp_s=rx,
        )

    def feed(self, msg: can.Message) -> list[DecodedSample | DecodedSync]:
        """Consume one frame; return what it completed (usually nothing or one item)."""
        c = self.counters
        c["frames"] += 1
        if msg.is_error_frame:
            self._problem("error_frame", msg, "error frame on the bus")
            return []
        if msg.is_remote_frame:
            self._problem("remote_frame", msg, "remote frames are not part of the protocol")
            return []
        lay = None if msg.is_extended_id else self._layouts.get(msg.arbitration_id)
        if lay is None:
            self._problem("unknown_id", msg, "identifier not in the DBC")
            return []
        data = msg.data
        if len(data) != lay.length:
            self._problem("bad_dlc", msg, f"{lay.name} has {lay.length} bytes")
            return []
        ctr = data[1] & 0x0F  # the DBC check pins the counter to bits 8..11
        if ctr >= COUNTER_MODULO:
            self._problem("bad_counter", msg, f"counter {ctr} is invalid (0..14)")
            return []
        crc = p01_crc(lay.frame_id, data, lay.e2e_length, lay.crc_byte)
        if data[lay.crc_byte] != crc:
            self._problem("bad_crc", msg, f"E2E CRC 0x{data[lay.crc_byte]:02X}, expected 0x{crc:02X}")
            return []
        fid = lay.frame_id
        last = self._last_ctr.get(fid)
        if last is not None:
            delta = counter_delta(ctr, last)
            if delta == 0:
                self._problem("repeated", msg, f"{lay.name} counter {ctr} repeated")
                return []
            if delta != 1:
                c["lost_frames"] += delta - 1
                self._problem("counter_jump", msg, f"{lay.name} counter {last} -> {ctr}: {delta - 1} lost")
        self._last_ctr[fid] = ctr
        rx = float(msg.timestamp)
        word = int.from_bytes(data, "little")
        role = lay.role
        if role == "sample_part":
            if self._group_words and ctr != self._group_ctr:
                got = ", ".join(self._layouts[i].name for i in self._group_words)
                self._problem("incomplete_sample", msg, f"sample {self._group_ctr} dropped, had only {got}")
                self._group_words.clear()
            self._group_ctr = ctr
            self._group_words[fid] = word
            if len(self._group_words) < self._n_parts:
                return []
            values: dict[str, float | int] = {}
            for pid, w in self._group_words.items():
                values.update(self._layouts[pid].decode_word(w))
            self._group_words.clear()
            return [self._sample(values, self._status, rx)]
        if role == "sample_fd":
            values = lay.decode_word(word)
            return [self._sample(values, int(values["StatusWord"]), rx)]
        if role == "sync":
            c["syncs"] += 1
            raw = lay.by_name["DeviceTime"].extract(word)
            return [DecodedSync(device_stamp_ns=self._sync_unwrap(raw), rx_timestamp_s=rx)]
        # status
        c["status"] += 1
        vals = lay.decode_word(word)
        self._status = int(vals["StatusWord"])
        if "SampleCount" in vals:
            self.last_sample_count = int(vals["SampleCount"])
        return []
