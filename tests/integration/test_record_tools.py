"""The recording tools on real ``hil sim`` recordings, as a user runs them (``hil ...``).

filter then merge gives the original messages back; merge of a split session equals the unsplit
one; cat, attachments and export read a real recording; recover turns a file cut at any byte
into one the plain mcap reader reads; every tool gives a bad file one line and exit 2.
"""

from __future__ import annotations

import csv
import json
import os
import re
import subprocess
from collections.abc import Callable, Iterator
from pathlib import Path

import pytest
from mcap.reader import make_reader
from mcap.writer import Writer

from hil.record.mcapio import read_session, split_parts
from tests.conftest import REPO, hil_cmd, run_hil

pytestmark = pytest.mark.slow


@pytest.fixture(scope="module")
def rec(tmp_path_factory: pytest.TempPathFactory) -> Iterator[dict[str, Path]]:
    tmp = tmp_path_factory.mktemp("tools")
    whole, split = tmp / "whole.mcap", tmp / "split.mcap"
    for path, extra in ((whole, []), (split, ["--split-mb", "0.25"])):
        proc = run_hil("sim", "--duration", "6", "--quiet", "--record", str(path), *extra, timeout=300)
        assert proc.returncode == 0, proc.stderr
    yield {"tmp": tmp, "whole": whole, "split": split}


def messages(path: Path) -> list[tuple[str, int, bytes]]:
    """(topic, log time, payload) in file order, read by the plain mcap reader (index and all)."""
    with open(path, "rb") as f:
        return [
            (c.topic, m.log_time, m.data) for _s, c, m in make_reader(f).iter_messages(log_time_order=False)
        ]


def hil_ok(*args: str) -> str:
    proc = run_hil(*args, timeout=300)
    assert proc.returncode == 0, proc.stdout + proc.stderr
    return proc.stdout


def test_a_filter_that_selects_nothing_or_one_part_of_a_split_session_says_so(rec: dict[str, Path]) -> None:
    tmp = rec["tmp"]
    proc = run_hil("filter", str(rec["whole"]), "-o", str(tmp / "none.mcap"), "--start", "100")
    assert proc.returncode == 0 and "hil filter: 0 messages" in proc.stdout, proc.stdout + proc.stderr
    assert "note: none of the" in proc.stderr and "span 6.0" in proc.stderr, proc.stderr
    proc = run_hil("filter", str(rec["split"]), "-o", str(tmp / "first.mcap"), "--topics", "/truth$")
    assert proc.returncode == 0, proc.stderr
    n = 1 + len(split_parts(rec["split"]))
    assert f"split.mcap is the first of {n} files of a split recording" in proc.stderr, proc.stderr
    assert "none of the" not in proc.stderr


def test_filter_by_time_then_merge_gives_the_original_messages(rec: dict[str, Path]) -> None:
    tmp, whole = rec["tmp"], rec["whole"]
    a, b, m = tmp / "a.mcap", tmp / "b.mcap", tmp / "ab.mcap"
    hil_ok("filter", str(whole), "-o", str(a), "--end", "2")
    hil_ok("filter", str(whole), "-o", str(b), "--start", "2")
    hil_ok("merge", str(a), str(b), "-o", str(m))
    orig = messages(whole)
    assert 0 < len(messages(a)) < len(orig)
    assert messages(m) == orig
    s = read_session(m)
    assert set(read_session(whole).metadata) | {"merge"} == set(s.metadata)  # no filter records
    assert s.attachments == read_session(whole).attachments


def test_filter_by_topics_then_merge_gives_every_topic_back_in_order(rec: dict[str, Path]) -> None:
    tmp, whole = rec["tmp"], rec["whole"]
    nav, rest, m = tmp / "nav.mcap", tmp / "rest.mcap", tmp / "navrest.mcap"
    hil_ok("filter", str(whole), "-o", str(nav), "--topics", "/nav/")
    hil_ok("filter", str(whole), "-o", str(rest), "--exclude-topics", "/nav/")
    assert {t for t, _l, _d in messages(nav)} == {t for t, _l, _d in messages(whole) if "/nav/" in t}
    hil_ok("merge", str(nav), str(rest), "-o", str(m))
    orig, got = messages(whole), messages(m)
    assert sorted(orig) == sorted(got)
    by_topic = lambda ms: {t: [x for x in ms if x[0] == t] for t in {x[0] for x in ms}}  # noqa: E731
    assert by_topic(got) == by_topic(orig)


def test_merge_of_a_split_session_is_the_unsplit_session(rec: dict[str, Path]) -> None:
    parts = sorted(rec["tmp"].glob("split*.mcap"))
    assert len(parts) >= 3, parts
    m = rec["tmp"] / "merged.mcap"
    out = hil_ok("merge", str(rec["split"]), "-o", str(m))  # one name: the session and its parts
    assert f"{len(parts)} files" in out
    assert messages(m) == messages(rec["whole"])  # hil sim is deterministic: same seed, same bytes
    proc = run_hil("rerun", str(m), "--verify", timeout=300)
    assert proc.returncode == 0 and "VERIFY OK" in proc.stdout, proc.stdout


def test_cat_prints_every_message_as_a_json_line(rec: dict[str, Path]) -> None:
    out = hil_ok("cat", str(rec["whole"]), "--topics", "^hil/.*/nav/ekf15$")  # not /foxglove/fix/nav/ekf15
    lines = [json.loads(ln) for ln in out.splitlines()]
    want = [x for x in messages(rec["whole"]) if x[0].startswith("hil/") and x[0].endswith("/nav/ekf15")]
    assert len(lines) == len(want) > 0
    assert [ln["message"] for ln in lines] == [json.loads(d) for _t, _l, d in want]
    assert {ln["schema"] for ln in lines} == {"hil.NavSolution"}
    # Foxglove's well-known types derived from it are protobuf: their bytes, as hex
    fox = [
        json.loads(ln)
        for ln in hil_ok("cat", str(rec["whole"]), "--topics", "^/foxglove/fix/nav/ekf15$").splitlines()
    ]
    assert (
        fox
        and {ln["schema"] for ln in fox} == {"foxglove.LocationFix"}
        and all("data_hex" in ln for ln in fox)
    )


def test_attachments_lists_and_extracts_the_scenario_dbc_and_schemas(rec: dict[str, Path]) -> None:
    listing = hil_ok("attachments", str(rec["whole"]))
    assert "can/imu.dbc" in listing and "schemas/hil.NavSolution.json" in listing and "scenario/" in listing
    out = rec["tmp"] / "att"
    hil_ok("attachments", str(rec["whole"]), "--extract", str(out), "--name", "can/imu.dbc")
    assert (out / "can" / "imu.dbc").read_bytes() == (REPO / "schemas" / "imu.dbc").read_bytes()
    proc = run_hil("attachments", str(rec["whole"]), "--extract", str(out), "--name", "nosuch")
    assert proc.returncode == 2 and "nosuch" in proc.stderr


@pytest.mark.parametrize("fmt", ["csv", "parquet"])
def test_export_writes_imu_gnss_truth_and_nav_tables(rec: dict[str, Path], fmt: str) -> None:
    out = rec["tmp"] / f"export-{fmt}"
    hil_ok("export", str(rec["whole"]), "--format", fmt, "-o", str(out))
    s = read_session(rec["whole"])
    for table, topic in (
        ("sensor_imu", "sensor/imu"),
        ("synced_gnss", "synced/gnss"),
        ("truth", "truth"),
        ("nav_ekf15", "nav/ekf15"),
    ):
        recs = s.by_topic(f"hil/bench/{topic}")
        first = json.loads(recs[0].payload)
        path = out / f"{table}.{fmt}"
        if fmt == "csv":
            with open(path, newline="") as f:
                rows = list(csv.DictReader(f))
            got = {k: rows[0][k] for k in ("seq", "stamp_ns")}
            assert got == {"seq": str(first["seq"]), "stamp_ns": str(first["stamp_ns"])}
        else:
            import pyarrow.parquet as pq

            t = pq.read_table(path)
            rows = t.to_pylist()
            assert rows[0]["seq"] == first["seq"] and rows[0]["log_time_ns"] == recs[0].log_time_ns
            if "pos_ned_m" in first:
                assert [rows[0][f"pos_ned_m_{a}"] for a in "ned"] == first["pos_ned_m"]
        assert len(rows) == len(recs) > 0


def test_recover_reads_a_file_cut_at_any_byte(rec: dict[str, Path]) -> None:
    data, orig = rec["whole"].read_bytes(), messages(rec["whole"])
    cut, fixed = rec["tmp"] / "cut.mcap", rec["tmp"] / "cut.fixed.mcap"
    for k in range(1, 7):
        cut.write_bytes(data[: len(data) * k // 7 + 13 * k])
        out = hil_ok("recover", str(cut), "-o", str(fixed))
        got = messages(fixed)
        assert got == orig[: len(got)] and len(got) >= len(read_session(cut).records), k
        assert "lost: " in out
    out = hil_ok("recover", str(rec["whole"]), "-o", str(fixed))
    assert messages(fixed) == orig and "nothing lost" in out


@pytest.mark.parametrize("cmd", [["recover"], ["filter"], ["merge"]])
def test_an_output_that_is_the_input_under_another_name_is_refused(
    rec: dict[str, Path], cmd: list[str]
) -> None:
    """A hard link (or a symlink) to the input as -o: refused before anything is opened, and
    the input is whole (the write would truncate the shared inode, then remove it as failed)."""
    tmp = rec["tmp"] / f"same-{cmd[0]}"
    tmp.mkdir()
    src = tmp / "in.mcap"
    src.write_bytes(rec["whole"].read_bytes())
    before = src.read_bytes()
    for link in (tmp / "hard.mcap", tmp / "soft.mcap"):
        if link.name.startswith("hard"):
            link.hardlink_to(src)
        else:
            link.symlink_to(src)
        proc = run_hil(cmd[0], str(src), "-o", str(link), timeout=60)
        assert proc.returncode == 2 and "is the input" in proc.stderr, (link.name, proc.stderr)
        assert src.read_bytes() == before and link.exists(), link.name


def test_info_and_report_give_each_stream_its_own_rate(rec: dict[str, Path]) -> None:
    """Rates over the messages' times of validity: the time sync releases what it held before
    its first lock at once, so over log times synced/imu of the 400 Hz IMU came out ~30 % high
    (and a 6 s run's nav rates far off); the one- and two-reader infos and the report agree."""
    from hil.record.info import info_json
    from hil.report.data import load

    path = str(rec["whole"])
    want = {"sensor/imu": 400.0, "synced/imu": 400.0, "nav/ekf15": 50.0, "synced/gnss": 10.0}
    for parallel in (False, True):
        rates = {c["topic"]: c["rate_hz"] for c in json.loads(info_json(path, parallel=parallel))["channels"]}
        for tail, hz in want.items():
            (got,) = [v for k, v in rates.items() if k.endswith("/" + tail)]
            assert got == pytest.approx(hz, rel=0.01), (parallel, tail, got)
    report = {t.topic: t.rate_hz for t in load(path).topics}
    for tail, hz in want.items():
        (got,) = [v for k, v in report.items() if k.endswith("/" + tail)]
        assert got == pytest.approx(hz, rel=0.01), ("report", tail, got)


def _foreign(path: Path) -> Path:
    with open(path, "wb") as f:
        w = Writer(f)
        w.start(profile="ros2", library="someone else")
        sid = w.register_schema("pkg/Msg", "ros2msg", b"int32 x")
        cid = w.register_channel("/x", "cdr", sid)
        w.add_message(cid, log_time=1, data=b"\x00\x01\x00\x00\x05\x00\x00\x00", publish_time=1)
        w.finish()
    return path


@pytest.mark.parametrize(
    "cmd",
    [["recover"], ["filter", "-o", "X"], ["merge", "-o", "X"], ["cat"], ["attachments"], ["export"]],
)
def test_a_bad_file_gets_one_line_and_exit_2(rec: dict[str, Path], cmd: list[str]) -> None:
    tmp = rec["tmp"] / f"bad-{cmd[0]}"
    tmp.mkdir()
    good = rec["whole"].read_bytes()
    files = {
        "garbage": b"this is not an mcap file\n" * 10,
        "empty": b"",
        "magic_only": good[:8],
        "header_cut": good[:30],
    }
    paths = {n: tmp / f"{n}.mcap" for n in files}
    for n, blob in files.items():
        paths[n].write_bytes(blob)
    paths["foreign"] = _foreign(tmp / "foreign.mcap")
    paths["missing"] = tmp / "missing.mcap"
    for name, path in paths.items():
        args = [cmd[0], str(path), *[str(tmp / "out.mcap") if x == "X" else x for x in cmd[1:]]]
        proc = run_hil(*args, timeout=60)
        assert proc.returncode == 2, (name, proc.stdout, proc.stderr)
        lines = [ln for ln in proc.stderr.splitlines() if ln.strip()]
        assert len(lines) == 1 and str(path) in lines[0] and "Traceback" not in proc.stderr, (
            name,
            proc.stderr,
        )
        assert not (tmp / "out.mcap").exists(), name  # nothing half-written left behind


def test_hil_sim_takes_the_options_it_shares_with_hil_up(rec: dict[str, Path]) -> None:
    path = rec["tmp"] / "opts.mcap"
    hil_ok(
        "sim",
        "--duration",
        "2",
        "--quiet",
        "--record",
        str(path),
        "--imu-rate",
        "200",
        "--record-exclude",
        "status/*",
    )
    topics = {t for t, _l, _d in messages(path)}
    assert topics and not [t for t in topics if "/status/" in t]
    imu = [t for t, _l, _d in messages(path) if t.endswith("/sensor/imu")]
    assert 380 <= len(imu) <= 420  # 2 s at 200 Hz
    proc = run_hil("sim", "--duration", "1", "--record", str(path), "--record-include", "nav/#", timeout=60)
    assert proc.returncode == 2 and "--record-include" in proc.stderr


@pytest.mark.parametrize("flag", ["--start", "--end"])
def test_filter_refuses_a_negative_time_as_replay_does(rec: dict[str, Path], flag: str) -> None:
    out = rec["tmp"] / f"neg{flag}.mcap"
    proc = run_hil("filter", str(rec["whole"]), "-o", str(out), flag, "-1", timeout=60)
    lines = [ln for ln in proc.stderr.splitlines() if ln.strip()]
    assert proc.returncode == 2 and len(lines) == 1 and f"{flag} -1" in lines[0], (
        proc.stderr
    )  # was taken as 0
    assert not out.exists()


def altered(
    src: Path, dest: Path, topic_end: str, alter: Callable[[bytes], bytes | None], nth: int = 10
) -> int:
    """``src`` rewritten with the ``nth`` message on the topic ending ``topic_end`` altered (left
    out when ``alter`` gives None); returns that message's MCAP sequence. Schemas, channels
    (metadata too), attachments, metadata kept."""
    with open(src, "rb") as f, open(dest, "wb") as out:
        reader = make_reader(f)
        w = Writer(out)
        w.start(profile="hil", library="test")
        schemas: dict[int, int] = {}
        chans: dict[int, int] = {}
        seen, seq = 0, -1
        for schema, chan, m in reader.iter_messages(log_time_order=False):
            if chan.id not in chans:
                sid = 0
                if schema is not None:
                    if schema.id not in schemas:
                        schemas[schema.id] = w.register_schema(schema.name, schema.encoding, schema.data)
                    sid = schemas[schema.id]
                chans[chan.id] = w.register_channel(
                    chan.topic, chan.message_encoding, sid, dict(chan.metadata)
                )
            data = m.data
            if chan.topic.startswith("hil/") and chan.topic.endswith(topic_end):
                if seen == nth:
                    data, seq = alter(data), m.sequence
                seen += 1
            if data is None:
                continue
            w.add_message(
                chans[chan.id],
                log_time=m.log_time,
                data=data,
                publish_time=m.publish_time,
                sequence=m.sequence,
            )
        f.seek(0)
        for a in make_reader(f).iter_attachments():
            w.add_attachment(a.create_time, a.log_time, a.name, a.media_type, a.data)
        f.seek(0)
        for md in make_reader(f).iter_metadata():
            w.add_metadata(md.name, dict(md.metadata))
        w.finish()
    assert seq >= 0
    return seq


def cut_in_half(data: bytes) -> bytes:
    return data[: len(data) // 2]


def test_export_says_how_many_payloads_it_could_not_decode(rec: dict[str, Path]) -> None:
    bad = rec["tmp"] / "bad-ekf15.mcap"
    seq = altered(rec["whole"], bad, "/nav/ekf15", cut_in_half)
    out = rec["tmp"] / "export-bad"
    proc = run_hil("export", str(bad), "-o", str(out), timeout=300)
    assert proc.returncode == 0, proc.stderr
    n = sum(1 for t, _l, _d in messages(rec["whole"]) if t.startswith("hil/") and t.endswith("/nav/ekf15"))
    with open(out / "nav_ekf15.csv", newline="") as f:
        assert len(list(csv.DictReader(f))) == n - 1
    note = [ln for ln in proc.stderr.splitlines() if "/nav/ekf15" in ln]  # it was silent
    assert len(note) == 1 and "1 payload(s) could not be decoded" in note[0] and f"seq {seq}," in note[0], (
        proc.stderr
    )


def test_export_of_a_bad_topic_pattern_is_one_line_and_exit_2(rec: dict[str, Path]) -> None:
    proc = run_hil("export", str(rec["whole"]), "--topics", "(", "-o", str(rec["tmp"] / "e"), timeout=60)
    lines = [ln for ln in proc.stderr.splitlines() if ln.strip()]
    assert proc.returncode == 2 and len(lines) == 1 and "'('" in lines[0], (
        proc.stderr
    )  # was re.error's traceback
    assert "Traceback" not in proc.stderr


def sequences(path: Path) -> dict[str, list[int]]:
    """Each topic's MCAP sequences in file order."""
    out: dict[str, list[int]] = {}
    with open(path, "rb") as f:
        for _s, c, m in make_reader(f).iter_messages(log_time_order=False):
            out.setdefault(c.topic, []).append(m.sequence)
    return out


def test_merged_split_parts_keep_the_foxglove_sequences_and_claim_no_part(rec: dict[str, Path]) -> None:
    m = rec["tmp"] / "merged-seq.mcap"
    hil_ok("merge", str(rec["split"]), "-o", str(m))
    got, want = sequences(m), sequences(rec["whole"])
    fox = [t for t in want if t.startswith("/foxglove/")]
    assert fox and {t: got[t] for t in fox} == {t: want[t] for t in fox}  # they restarted at 0 in each part
    comp = read_session(m).metadata["completeness"]
    assert "part" not in comp and "parts" not in comp, comp
    info = hil_ok("info", str(m), "--no-accuracy")
    assert "split part=" not in info, info
    rows = [ln.split() for ln in info.splitlines() if ln.startswith("/foxglove/")]
    assert rows and all(r[-1] == "0" for r in rows), info  # dups 1 on every /foxglove row


def test_merge_refuses_an_input_given_twice_or_another_run(rec: dict[str, Path]) -> None:
    tmp, whole = rec["tmp"], rec["whole"]
    link = tmp / "whole-link.mcap"
    link.symlink_to(whole)
    other = tmp / "other-run.mcap"
    hil_ok("sim", "--scenario", "static", "--duration", "2", "--quiet", "--record", str(other))
    out = tmp / "mix.mcap"
    for inputs, said in (
        ([whole, whole], "given twice"),
        ([whole, link], "given twice"),
        ([whole, other], "another run"),
    ):
        proc = run_hil("merge", *map(str, inputs), "-o", str(out), timeout=120)
        lines = [ln for ln in proc.stderr.splitlines() if ln.strip()]
        assert proc.returncode == 2 and len(lines) == 1 and said in lines[0], (inputs, proc.stderr)
        assert not out.exists(), inputs  # it was written, doubled or mixed, without a word
    assert "scenario static (not straight_level)" in lines[0], lines


def test_rerun_of_a_recovered_file_does_not_call_inputs_after_the_last_journal_lost(
    rec: dict[str, Path],
) -> None:
    tmp = rec["tmp"]
    cut, fixed = tmp / "rr-cut.mcap", tmp / "rr-cut.recovered.mcap"
    data = rec["whole"].read_bytes()
    cut.write_bytes(data[: len(data) * 2 // 3])
    hil_ok("recover", str(cut), "-o", str(fixed))
    proc = run_hil("rerun", str(fixed), "--core", "fusion", "--verify", timeout=300)
    assert proc.returncode == 0 and "VERIFY OK" in proc.stdout, proc.stdout + proc.stderr
    assert "were lost" not in proc.stdout, proc.stdout  # it held more than journaled: not a loss
    # and fewer held than journaled is still said: one synced IMU sample left out
    gone = tmp / "rr-gone.mcap"
    altered(rec["whole"], gone, "/synced/imu", lambda _d: None, nth=100)
    proc = run_hil("rerun", str(gone), "--core", "fusion", timeout=300)
    assert "holds only" in proc.stdout and "1 inputs were lost" in proc.stdout, proc.stdout + proc.stderr


@pytest.mark.parametrize("cmd", [["info", "--no-accuracy"], ["attachments"], ["cat"], ["recover", "-o", "X"]])
def test_a_closed_stdout_ends_any_command_quietly(rec: dict[str, Path], cmd: list[str]) -> None:
    """`hil info f | head -1`: the reader left; exit 0 as `hil cat` does, nothing on stderr (it was
    "hil: BrokenPipeError" and exit 2). The pipe is closed before the command writes: no race."""
    r, w = os.pipe()
    os.close(r)  # every write to w now fails with EPIPE
    out = rec["tmp"] / f"pipe-{cmd[0]}.mcap"
    args = [cmd[0], str(rec["whole"]), *[str(out) if x == "X" else x for x in cmd[1:]]]
    try:
        proc = subprocess.run(
            hil_cmd(*args), stdout=w, stderr=subprocess.PIPE, text=True, cwd=REPO, timeout=300
        )
    finally:
        os.close(w)
    assert proc.returncode == 0 and proc.stderr == "", proc.stderr


def string_stamp(data: bytes) -> bytes:
    return re.sub(rb'"stamp_ns":(\d+)', rb'"stamp_ns":"\1"', data, count=1)


@pytest.mark.parametrize("alter", [cut_in_half, string_stamp])
@pytest.mark.parametrize("cmd", [["info"], ["rerun", "--verify"]])
def test_a_payload_that_does_not_decode_is_named_in_one_line(
    rec: dict[str, Path], cmd: list[str], alter: Callable[[bytes], bytes]
) -> None:
    bad = rec["tmp"] / f"bad-{cmd[0]}-{alter.__name__}.mcap"
    seq = altered(rec["whole"], bad, "/nav/ekf15", alter)
    proc = run_hil(cmd[0], str(bad), *cmd[1:], timeout=300)
    if cmd[0] == "rerun" and alter is string_stamp:
        # verify compares the recorded bytes with the recomputed ones before decoding them: a
        # string stamp is that output differing, named, exit 1 (a finding, not a bad file)
        assert proc.returncode == 1 and "VERIFY FAILED" in proc.stdout, proc.stdout + proc.stderr
        assert f"nav/ekf15 seq {seq}" in proc.stdout and "Traceback" not in proc.stderr, proc.stdout
        return
    lines = [ln for ln in proc.stderr.splitlines() if ln.strip()]
    assert proc.returncode == 2 and len(lines) == 1 and "Traceback" not in proc.stderr, (
        proc.stdout + proc.stderr
    )
    # it was "hil: DecodeError: Input data was truncated": no file, topic or message
    for said in (str(bad), "nav/ekf15", f"seq {seq} ", "log_time_ns ", "hil filter", "--exclude-topics"):
        assert said in lines[0], (said, lines[0])


def _chunks(path: Path) -> list[tuple[int, int, int]]:
    """(offset, record length, messages) of each chunk, from the file's summary, in file order."""
    with open(path, "rb") as f:
        summary = make_reader(f).get_summary()
    assert summary is not None
    out = []
    for c in sorted(summary.chunk_indexes, key=lambda c: c.chunk_start_offset):
        n = (c.message_index_length - 15 * len(c.message_index_offsets)) // 16
        out.append((c.chunk_start_offset, c.chunk_length, n))
    return out


def _spans(text: str) -> list[tuple[float, float]]:
    import re

    return [(float(a), float(b)) for a, b in re.findall(r"log time (\d+\.\d+)\.\.(\d+\.\d+) s", text)]


def _recover_a_damaged_middle_chunk(
    rec: dict[str, Path], name: str, damage: Callable[[bytearray, int, int], None]
) -> tuple[Path, int, int, str]:
    """The middle chunk of the 6 s sim damaged (``damage(data, offset, length)``) and the file
    recovered: the copy holds the original's messages but that chunk's, none altered. Returns
    (damaged file, the chunk's offset, its messages, recover's output)."""
    from collections import Counter

    orig = messages(rec["whole"])
    chunks = _chunks(rec["whole"])
    offset, length, n_chunk = chunks[len(chunks) // 2]
    data = bytearray(rec["whole"].read_bytes())
    damage(data, offset, length)
    bad, fixed = rec["tmp"] / f"{name}.mcap", rec["tmp"] / f"{name}.fixed.mcap"
    bad.write_bytes(bytes(data))
    out = hil_ok("recover", str(bad), "-o", str(fixed))
    got = messages(fixed)
    assert not Counter(got) - Counter(orig), "a message that is not the original's was kept"
    assert len(orig) - len(got) == n_chunk > 0, (len(orig), len(got), n_chunk)
    return bad, offset, n_chunk, out


# a chunk record: opcode (1), length (8), start and end time (8 + 8), uncompressed size (8), then
# the uncompressed data's CRC-32
_CHUNK_CRC_AT = 1 + 8 + 8 + 8 + 8


@pytest.mark.parametrize("where", ["its CRC", "its data"])
def test_recover_of_a_damaged_chunk_keeps_only_the_original_messages(
    rec: dict[str, Path], where: str
) -> None:
    """A bit flipped in a middle chunk: the copy holds the original's messages but that chunk's,
    none altered, says so, and its completeness no longer claims replay_ready. In the stored CRC
    the data decompresses and the CRC catches it; in the compressed data zstd itself may (at
    level 1 it did, at level 3 the CRC had)."""
    name = "bit-crc" if where == "its CRC" else "bit-data"

    def flip_a_bit(d: bytearray, at: int, n: int) -> None:
        d[at + (_CHUNK_CRC_AT if where == "its CRC" else n // 2)] ^= 1

    bad, offset, n_chunk, out = _recover_a_damaged_middle_chunk(rec, name, flip_a_bit)
    fixed = bad.with_name(f"{name}.fixed.mcap")
    why = "its CRC does not match" if where == "its CRC" else r"(its CRC does not match|zstd: [^\n]*)"
    said = rf"the chunk at byte {offset}: {why} \(damaged\); none of its {n_chunk} messages kept"
    assert re.search(said, out), out
    assert all(a <= b for a, b in _spans(out)), out
    info = hil_ok("info", str(fixed))
    assert "replay_ready=true" not in info and "replay_ready=false" in info, info
    assert f"recovered: a copy hil recover made of {bad.name}; lost 1 chunk(s) ({n_chunk} messages)" in info
    proc = run_hil("cat", str(bad), "--topics", "/truth$", timeout=120)
    assert proc.returncode == 0 and f"hil cat: note: the chunk at byte {offset}" in proc.stderr, proc.stderr
    assert "replay_ready=true" in hil_ok("info", str(rec["whole"]))  # the intact original still is


def test_recover_goes_past_a_garbled_record_length_on_the_summarys_index(rec: dict[str, Path]) -> None:
    """A middle chunk's record length garbled in a finished file: nothing after it could be
    read (recover stopped there, the rest of the session lost). The summary lists every chunk:
    reading goes on at the next one, and only the damaged chunk's messages are missing."""

    def garble_length(d: bytearray, at: int, _n: int) -> None:
        d[at + 1 : at + 9] = (2**40).to_bytes(8, "little")  # the chunk record's length

    bad, offset, _n, out = _recover_a_damaged_middle_chunk(rec, "length", garble_length)
    assert f"garbage at byte {offset}" in out and "reading goes on at the next chunk" in out, out
    assert messages(bad.with_name("length.fixed.mcap"))[-1] == messages(rec["whole"])[-1]  # the end is there


def test_a_cut_inside_a_chunk_record_is_a_cut_not_garbage(rec: dict[str, Path]) -> None:
    """A file cut inside a chunk (its length runs past the file's end) is a crash's cut: named as
    one, and the messages complete in its prefix are kept, never called garbage."""
    data, orig = rec["whole"].read_bytes(), messages(rec["whole"])
    offset, length, _n = _chunks(rec["whole"])[0]  # longer than what comes before it: the QA case
    assert length > offset
    cut, fixed = rec["tmp"] / "cutchunk.mcap", rec["tmp"] / "cutchunk.fixed.mcap"
    for at in (offset + 4, offset + 9 + 60, offset + length * 2 // 3):
        cut.write_bytes(data[:at])
        out = hil_ok("recover", str(cut), "-o", str(fixed))
        assert "garbage" not in out, (at, out)
        if at > offset + 9:
            assert f"the file ends inside a chunk record at byte {offset}" in out, (at, out)
        else:
            assert f"a record header cut off at byte {offset}" in out, (at, out)
        got = messages(fixed)
        assert got == orig[: len(got)], at
        assert all(a <= b for a, b in _spans(out)), out


def test_cat_and_attachments_say_what_a_cut_file_lost(rec: dict[str, Path]) -> None:
    data = rec["whole"].read_bytes()
    tmp = rec["tmp"]
    cut = tmp / "cut-cat.mcap"
    cut.write_bytes(data[: len(data) // 2])
    proc = run_hil("cat", str(cut), "--topics", "/truth$", timeout=120)
    assert proc.returncode == 0 and proc.stdout, proc.stderr
    assert "hil cat: note: " in proc.stderr and "unreadable" in proc.stderr, proc.stderr
    whole = run_hil("cat", str(rec["whole"]), "--topics", "/truth$", timeout=120)
    assert whole.returncode == 0 and "note" not in whole.stderr, whole.stderr
    short = tmp / "cut-att.mcap"
    short.write_bytes(data[:5000])
    proc = run_hil("attachments", str(short), timeout=60)
    listed = [ln for ln in proc.stdout.splitlines() if ln.strip()]
    assert proc.returncode == 0 and 0 < len(listed) < len(
        hil_ok("attachments", str(rec["whole"])).splitlines()
    )
    assert "hil attachments: note: the file ends inside an attachment record" in proc.stderr, proc.stderr
