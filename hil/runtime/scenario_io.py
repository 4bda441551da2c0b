"""Scenario plumbing between processes: every service rebuilds the run's scenario from RunInfo.

The scenario text travels in ``RunInfo`` so services on other hosts (or containers) need no shared
file system, and the recording holds the exact text as an attachment.
"""

from __future__ import annotations

import hashlib
import json
import os
from pathlib import Path

from hil.messages import CONTRACT_TYPES, RunInfo, json_schema, schema_name
from hil.nav.scenario import Scenario, parse_scenario
from hil.nav.scenario import scenario_for_run as scenario_for_run  # re-exported: the services' import

REPO_ROOT = Path(__file__).resolve().parents[2]


def dbc_path() -> Path:
    return Path(os.environ.get("HIL_DBC") or REPO_ROOT / "schemas" / "imu.dbc")


def scenario_from_text(text: str, name: str = "scenario") -> Scenario:
    """Parse scenario TOML text with the same parser as files."""
    return parse_scenario(text, default_name=name)


def sha256_text(text: str) -> str:
    return hashlib.sha256(text.encode()).hexdigest()


def run_attachments(run: RunInfo) -> list[tuple[str, bytes, str]]:
    """What a recording carries besides messages: scenario, DBC, schemas."""
    out = [(f"scenario/{run.scenario}.toml", run.scenario_toml.encode(), "application/toml")]
    dbc = dbc_path()
    if dbc.is_file():
        out.append(("can/imu.dbc", dbc.read_bytes(), "text/plain"))
    for cls in CONTRACT_TYPES:
        out.append(
            (
                f"schemas/{schema_name(cls)}.json",
                json.dumps(json_schema(cls), indent=2).encode(),
                "application/schema+json",
            )
        )
    return out
