"""Which message type each publisher sends, so a subscriber refuses a key whose publisher disagrees.

Every typed publisher declares a liveliness token ``<key>/@type/<type>~<hash>`` (the type with
``~`` for ``/``; the hash is of the type's full ros2msg definition, nested types included, so two
builds whose .msg files differ disagree even under the same type name). Every typed subscription
watches the tokens under its key expression (history included: publishers that came first are
checked at subscription time) and refuses a key whose publisher declares another type or schema:
its samples are dropped and counted as ``type_mismatch``, and one error names both types. When the
disagreeing publisher goes away the key is accepted again.
"""

from __future__ import annotations

import hashlib
from dataclasses import dataclass
from functools import cache

from shared import msgs

TYPE_CHUNK = "@type"


@cache
def type_hash(msgtype: str) -> str:
    return hashlib.sha256(msgs.schema_text(msgtype).encode()).hexdigest()[:16]


def token_key(key: str, msgtype: str) -> str:
    return f"{key}/{TYPE_CHUNK}/{msgtype.replace('/', '~')}~{type_hash(msgtype)}"


def watch_expr(key_expr: str) -> str:
    """The liveliness key expression of the type tokens of every publisher under ``key_expr``."""
    return f"{key_expr}/{TYPE_CHUNK}/*"


@dataclass(frozen=True)
class Declared:
    key: str
    msgtype: str
    schema: str


def parse_token(token: str) -> Declared | None:
    """The key, type and schema hash a token declares (None: not a type token)."""
    key, sep, rest = token.rpartition(f"/{TYPE_CHUNK}/")
    name, _, schema = rest.rpartition("~")
    if not sep or not key or not name or not schema:
        return None
    return Declared(key, name.replace("~", "/"), schema)


def mismatch(declared: Declared, expected: str) -> str | None:
    """Why a publisher declaring ``declared`` cannot feed a subscriber of ``expected`` (None: it can)."""
    if declared.msgtype != expected:
        return (f"publisher on {declared.key} sends {declared.msgtype} (schema {declared.schema}); "
                f"this subscriber expects {expected} (schema {type_hash(expected)})")
    if declared.schema != type_hash(expected):
        return (f"publisher on {declared.key} sends {declared.msgtype} with schema {declared.schema}; this "
                f"subscriber's {expected} has schema {type_hash(expected)} (different .msg definitions)")
    return None


def track(publishers: dict[str, set[str]], key: str, token: str, gone: bool) -> None:
    """Keeps ``publishers`` (key -> the type tokens of its live publishers) up to date with one token."""
    live = publishers.setdefault(key, set())
    if gone:
        live.discard(token)
    else:
        live.add(token)
    if not live:
        del publishers[key]
