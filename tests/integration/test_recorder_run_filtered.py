"""A recorder whose key filter leaves the run key out (``hil up --record-include 'nav/**'``)
still takes the run's ``RunInfo``: the file's metadata, attachments and time base are the run's,
not raw receive times with no metadata (``hil rerun``: "not a rig session")."""

from __future__ import annotations

import time
from collections.abc import Iterator
from pathlib import Path

import pytest

from hil.bus.identity import UNKNOWN
from hil.bus.keys import Keys
from hil.bus.session import BusConfig, open_session
from hil.messages import encode
from hil.record.mcapio import read_session
from hil.runtime.service import ServiceContext
from services.recorder import Recorder
from tests.conftest import free_port
from tests.integration.test_recorder_loss_and_crash import RIG, imu, run_info


@pytest.fixture
def session() -> Iterator[object]:
    s = open_session(BusConfig(mode="peer", listen=(f"tcp/127.0.0.1:{free_port()}",), connect=()))
    try:
        yield s
    finally:
        s.close()


@pytest.mark.parametrize("include", [["sensor/**"], []])
def test_a_filter_that_leaves_the_run_out_still_takes_its_time_base_and_metadata(
    session: object, tmp_path: Path, include: list[str]
) -> None:
    path = tmp_path / "filtered.mcap"
    rec = Recorder(
        ServiceContext(
            name="recorder", rig=RIG, session=session, options={"path": str(path), "include": include}
        )
    )
    k = Keys(RIG)
    run = run_info(0)
    rx = time.time_ns()
    # as the Zenoh callback enqueues: (key, payload, receive wall time, publisher, origin, encoding)
    rec.queue.put("run", "", (k.run(), encode(run), rx, "", UNKNOWN, None))
    for i in range(1, 5):
        rec.queue.put("sensor/imu", "", (k.sensor("imu"), encode(imu(i)), rx, "", UNKNOWN, None))
    rec.setup()
    rec.teardown()
    s = read_session(path)
    assert {r.topic for r in s.records} == ({k.sensor("imu")} if include else {k.run(), k.sensor("imu")})
    assert s.metadata["hil"]["start_epoch_ns"] == str(run.start_epoch_ns)
    assert s.metadata["hil"]["scenario"] == "straight_level"
    assert s.attachments, "the run's scenario attachments"
    imus = [r for r in s.records if r.topic == k.sensor("imu")]
    # the samples on the rig's time base: start epoch + their stamps, not their receive times
    assert [r.publish_time_ns - run.start_epoch_ns for r in imus] == [i * 2_500_000 for i in range(1, 5)]
