"""What a subscription does with each payload on one key: built once per key, run per sample.

``taker`` binds everything a payload needs (the key's received meter, its type's size limit,
decoder and the checks the type can fail, shared/runtime/validate.py) into one function, so a
sample costs no lookups by key or type: what remains is mostly decoding (bench/runtime.py
measures the runtime against raw Zenoh).
"""

from __future__ import annotations

import functools
from collections.abc import Callable
from time import monotonic
from typing import Any

import zenoh

from shared import msgs
from shared.runtime import validate
from shared.runtime.clock import Clock

Take = Callable[[bytes], Any]


def taker(key: str, msgtype: str, tick: Callable[[float], None], clock: Clock,
          reject: Callable[[str, str, str], None]) -> Take:
    """``take(payload)``: ticks the key's received meter, checks the size, decodes and validates;
    returns the message, or None for a payload it passed to ``reject(key, reason, detail)``.
    ``msgtype`` "raw" gives the payload itself."""
    if msgtype == "raw":
        def take_raw(payload: bytes) -> bytes:
            tick(monotonic())
            return payload
        return take_raw
    try:
        decode, stamped = msgs.decoder(msgtype), "header" in msgs.msg_class(msgtype).__dataclass_fields__
    except msgs.MessageError:  # an unknown type: every sample is rejected, as malformed
        decode, stamped = functools.partial(msgs.deserialize, msgtype=msgtype), False
    check, limit = validate.checker(msgtype), validate.max_payload(msgtype)

    def take(payload: bytes) -> Any:
        tick(monotonic())
        try:
            if len(payload) > limit:
                validate.check_size(len(payload), msgtype)
            msg = decode(payload)
            if check is not None:
                check(msg, clock.reference() if stamped else None)
        except msgs.MessageError as exc:
            reject(key, "malformed", str(exc))
            return None
        except validate.RejectedError as exc:
            reject(key, exc.reason, exc.detail)
            return None
        return msg
    return take


def exact_key(key_expr: str) -> str:
    """``key_expr`` in canonical form when it names one key (no wildcard), else "": a subscription
    to one key need not read each sample's."""
    if "*" in key_expr or "$" in key_expr:
        return ""
    try:
        return str(zenoh.KeyExpr.autocanonize(key_expr))
    except zenoh.ZError:  # declaring the subscriber says what is wrong with it
        return ""
