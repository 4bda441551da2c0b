"""The bus says what it carries: typed encodings, liveliness tokens and a topic queryable.

A tool that joins a rig's Zenoh network needs none of our source to read it:

- **Encoding.** Every rig publication's Zenoh encoding names its type:
  ``application/json;hil.NavSolution`` (``encoding_of``), the schema name being the MCAP schema
  name and the title of ``schemas/hil.NavSolution.json``. A subscriber reads it from
  ``sample.encoding``.
- **Liveliness.** Every service declares the liveliness token ``hil/<rig>/@alive/<service>``
  for as long as its process lives (``session.liveliness().get("hil/*/@alive/*")`` lists the
  running services of every rig; a liveliness subscriber sees them come and go).
- **Topics.** Every service answers queries on ``hil/<rig>/@topics/<service>`` with one JSON
  reply (encoding ``application/json;hil.Topics``): ``{"rig", "service", "topics": {key:
  type}, "schemas": {type: JSON Schema}}`` for every key it publishes. ``session.get(
  "hil/<rig>/@topics/*")`` therefore returns the rig's whole key table with the schemas.

Why ``@`` chunks: Zenoh never matches a verbatim chunk (``@alive``, ``@topics``) with ``*`` or
``**``, so the recorder's ``hil/<rig>/**`` and every other rig subscription stay exactly as
they were, and nothing of this is ever recorded. ``docs/topics.md`` has a ten-line zenoh-python
example (tested against a live ``hil up``).
"""

from __future__ import annotations

import contextlib
import functools
import json
import threading
from typing import Any

import zenoh

from hil.messages import Message, json_schema, schema_name

ALIVE = "@alive"
TOPICS = "@topics"
TOPICS_SCHEMA = "hil.Topics"


@functools.cache
def encoding_of(cls: type[Message]) -> zenoh.Encoding:
    """``application/json;hil.<Type>``: JSON, and which contract type."""
    return zenoh.Encoding.APPLICATION_JSON.with_schema(schema_name(cls))


def alive_key(rig: str, service: str) -> str:
    return f"hil/{rig}/{ALIVE}/{service}"


def topics_key(rig: str, service: str) -> str:
    return f"hil/{rig}/{TOPICS}/{service}"


class BusDescription:
    """One service's part of the self-description: its token, its queryable, its key table.

    ``add`` may be called at any time (a node declares an output on first use); a query always
    gets the table as it is then. ``close`` undeclares both (a closing session does it too).
    """

    def __init__(self, session: zenoh.Session, rig: str, service: str) -> None:
        self.session = session
        self.rig = rig
        self.service = service
        self._lock = threading.Lock()
        self._topics: dict[str, type[Message]] = {}
        self._token: Any = None
        self._queryable: Any = None

    def add(self, key: str, cls: type[Message]) -> None:
        with self._lock:
            self._topics[key] = cls

    def declare(self) -> None:
        """Token and queryable on the bus; errors are the caller's (a session that cannot)."""
        self._queryable = self.session.declare_queryable(topics_key(self.rig, self.service), self._on_query)
        self._token = self.session.liveliness().declare_token(alive_key(self.rig, self.service))

    def table(self) -> dict[str, Any]:
        with self._lock:
            topics = dict(self._topics)
        return {
            "rig": self.rig,
            "service": self.service,
            "topics": {k: schema_name(c) for k, c in sorted(topics.items())},
            "schemas": {schema_name(c): json_schema(c) for c in set(topics.values())},
        }

    def _on_query(self, query: zenoh.Query) -> None:
        try:  # Zenoh's thread: never raise into it
            payload = json.dumps(self.table(), sort_keys=True).encode()
            with query:  # the reply is final once the query is released
                query.reply(
                    topics_key(self.rig, self.service),
                    payload,
                    encoding=zenoh.Encoding.APPLICATION_JSON.with_schema(TOPICS_SCHEMA),
                )
        except Exception:  # a query that cannot be answered is the asker's timeout
            return

    def close(self) -> None:
        for thing in (self._token, self._queryable):
            if thing is not None:
                with contextlib.suppress(Exception):  # the session may already be closing
                    thing.undeclare()
        self._token = self._queryable = None
