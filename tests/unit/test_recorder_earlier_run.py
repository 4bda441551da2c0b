"""A restarted recorder takes the run from its earlier files when their RunInfo messages were
filtered out (``--record-include 'nav/**'``): from the ``hil`` metadata and scenario attachment
a recorder wrote (``Recorder._write_run_metadata``)."""

from __future__ import annotations

from pathlib import Path
from types import SimpleNamespace

import msgspec

from hil.messages import RunInfo, decode
from hil.record.mcapio import SessionWriter, iter_records
from hil.runtime.options import RecorderOptions
from services.recorder import Recorder, _RunFromMetadata
from tests.replay.helpers import GOLDEN


def _golden_run() -> RunInfo:
    for kind, rec in iter_records(GOLDEN):
        if kind == "message" and rec.schema == "hil.RunInfo":
            return decode(RunInfo, rec.payload)
    raise AssertionError("the golden recording holds no RunInfo")


def test_the_run_from_a_recorders_metadata_is_its_runinfo(tmp_path: Path) -> None:
    # GIVEN a file whose recorder took a live run (speed 2, the golden scenario) and wrote its
    # metadata and attachments, and no RunInfo message
    run = msgspec.structs.replace(_golden_run(), seq=7, stamp_ns=5_000_000_000, speed=2.0)
    path = tmp_path / "s.mcap"
    writer = SessionWriter(path)
    recorder = SimpleNamespace(writer=writer, _meta_written=False, opts=RecorderOptions(path=str(path)))
    Recorder._write_run_metadata(recorder, run)  # type: ignore[arg-type]
    writer.close()
    # WHEN the run is read back from the file alone
    earlier = _RunFromMetadata()
    for kind, rec in iter_records(path):
        earlier.take(kind, rec)
    # THEN it is that RunInfo (its seq and stamp aside): time base, identity, scenario
    assert run.scenario_toml
    assert earlier.run() == msgspec.structs.replace(run, seq=0, stamp_ns=0)


def test_a_file_without_a_start_epoch_gives_no_run() -> None:
    earlier = _RunFromMetadata()
    earlier.take("metadata", SimpleNamespace(name="hil", metadata={"rig": "x"}))
    assert earlier.run() is None  # the recorder waits for a RunInfo, as before
