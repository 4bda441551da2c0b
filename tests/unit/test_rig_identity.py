"""The rig's identity on the bus (``hil.bus.identity``): ids Zenoh accepts, that prove
themselves with the run's key and with nothing else."""

from __future__ import annotations

import json

import zenoh

from hil.bus.identity import FOREIGN, RIG, UNKNOWN, RigIdentity, is_rig_zid, new_rig_key, rig_zid


def test_a_rig_zid_is_a_zenoh_id_and_proves_itself_with_the_key_only() -> None:
    key, other = new_rig_key(), new_rig_key()
    zids = {rig_zid(key) for _ in range(50)}
    assert len(zids) == 50  # fresh each time: a restarted service gets a new one
    for z in zids:
        assert len(z) == 32 and z[0] != "0" and is_rig_zid(key, z) and not is_rig_zid(other, z)
    forged = next(iter(zids))[:16] + "0" * 16
    assert not is_rig_zid(key, forged)


def test_zenoh_opens_a_session_under_the_id_and_names_its_samples_with_it() -> None:
    key = new_rig_key()
    zid = rig_zid(key)
    conf = zenoh.Config()
    conf.insert_json5("mode", '"peer"')
    conf.insert_json5("scouting/multicast/enabled", "false")
    conf.insert_json5("listen/endpoints", '["tcp/127.0.0.1:0"]')
    conf.insert_json5("id", json.dumps(zid))
    s = zenoh.open(conf)
    try:
        assert str(s.info.zid()) == zid
        pub = s.declare_publisher("hil/idtest/x")
        source = f"{pub.id.zid}:{pub.id.eid}"
        ident = RigIdentity(key)
        assert ident.classify(source) == RIG
        assert ident.classify("1234567890abcdef1234567890abcdef:3") == FOREIGN
        assert ident.classify("") == FOREIGN  # a plain publisher without source info
        assert RigIdentity(None).classify(source) == UNKNOWN
        pub.undeclare()
    finally:
        s.close()
