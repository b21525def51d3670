"""The node: one service instance's window onto Zenoh, bridged into asyncio.

Zenoh callbacks run on Zenoh threads; they copy the payload and hand it to the event loop with
``call_soon_threadsafe``, once per batch: samples that arrive while one is pending join it. Each
subscription owns a bounded queue with an explicit policy: ``latest(n)`` keeps the newest n
samples (control loops), ``fifo(n)`` keeps all up to n waiting (bulk consumers; a batch being
handled has left the queue); whatever a policy discards is counted per key ("dropped" in @health).
A payload that is malformed or unfit (shared/runtime/validate.py) is counted per key and reason
("rejected") and never reaches the handler. Handlers run on the loop, so a slow handler never
blocks Zenoh. A ``fifo`` subscription handles every sample, so its samples are decoded and
validated on the Zenoh thread as they arrive, beside the loop rather than on it; a ``latest``
subscription decodes on the loop only the samples its policy kept. Warnings about bad input are
rate-limited per kind.

A subscription made ``inline`` skips the hop, for handlers that only store the newest value or
put it on a thread-safe queue, where the hop is most of the latency: its plain, thread-safe
handler runs on the Zenoh thread as each sample arrives, decoded and validated as usual, without
a queue of its own (the transport's buffers are its queue). It holds Zenoh's receive thread while
it decodes and handles: for large or frequent messages the loop is the faster path
(bench/runtime.py measures both).
"""

from __future__ import annotations

import asyncio
import collections
import functools
import inspect
import json
import logging
import os
import threading
import time
from collections.abc import Awaitable, Callable
from typing import Any

import zenoh

from shared import keys as keyreg
from shared import msgs
from shared.ports import QueuePolicy, fifo, latest
from shared.runtime import inbound, schemas, shm
from shared.runtime.clock import Clock
from shared.runtime.logs import RateLimitedLog, fields
from shared.runtime.stats import RateMeter, Stats, Tally
from shared.runtime.zsession import declare_publisher, declare_subscriber
from shared.wiring import Binding

__all__ = ["Node", "Publisher", "QueuePolicy", "RateMeter", "Subscription", "fifo", "latest"]

LOG_SUMMARY_S = 10.0  # a recurring warning is summarised at most this often


class Publisher:
    """Typed puts on one key. ``block``: when the transport is congested, ``put`` waits instead of
    dropping (for bulk transfers that must arrive whole; a control loop wants the default, drop).
    A payload of ``shm.MIN_BYTES`` or more of a sensor type (``shm.POOL_TYPES``) goes out from the
    process's shared-memory pool (shared/runtime/shm.py), as bytes when the pool is unavailable or
    full (counted)."""

    def __init__(self, node: Node, key: str, msgtype: str, block: bool = False, cache_last: bool = False) -> None:
        self.key = key
        self.msgtype = msgtype
        self._node = node
        congestion = zenoh.CongestionControl.BLOCK if block else zenoh.CongestionControl.DROP
        self._pub = declare_publisher(node.session, key, congestion, cache_last)
        self._type_token = node.session.liveliness().declare_token(schemas.token_key(key, msgtype))
        self._write = msgs.pieces_writer(msgtype)
        self.meter = node.stats.published.setdefault(key, RateMeter())
        self.shm_sent = 0  # payloads put from the shared-memory pool
        self._pool_min = shm.MIN_BYTES if msgtype in shm.POOL_TYPES else float("inf")
        self._put, self._tick = self._pub.put, self.meter.tick  # bound once: put runs per message

    def put(self, msg: Any) -> None:
        pieces, size = self._write(msg)
        if size < self._pool_min:
            self._put(b"".join(pieces))
        else:
            self._put_large(pieces, size)
        self._tick(time.monotonic())

    def put_bytes(self, payload: bytes) -> None:
        if len(payload) < self._pool_min:
            self._put(payload)
        else:
            self._put_large([payload], len(payload))
        self._tick(time.monotonic())

    def _put_large(self, pieces: list, size: int) -> None:
        buf, why = shm.POOL.buffer(pieces, size)
        if buf is None:
            self._node.stats.count(why, self.key)
            self._pub.put(b"".join(pieces))
        else:
            self._pub.put(buf)
            self.shm_sent += 1


class Subscription:
    def __init__(self, node: Node, key_expr: str, msgtype: str | None,
                 handler: Callable[..., Any], policy: QueuePolicy, inline: bool = False, history: bool = False) -> None:
        if inline and inspect.iscoroutinefunction(handler):
            raise TypeError(f"subscription to {key_expr}: an inline handler must be a plain function, not a coroutine")
        self.key_expr = key_expr
        self.inline = inline
        self.msgtype = msgtype
        self.policy = policy
        self._node = node
        self._handler = handler
        self._wants_key = _arity(handler) >= 2
        self._queue: collections.deque = collections.deque(
            maxlen=policy.depth if policy.kind == "latest" else None)
        self._lock = threading.Lock()
        self._scheduled = False
        self._whole_batches = policy.kind == "fifo"  # keep-latest pops one at a time (no new queue per batch)
        # fifo: every sample is handled, so it is decoded on arrival (Zenoh thread) and queued decoded
        self._decoded = policy.kind == "fifo"
        self._loop = node.loop
        # Plain functions run straight from the loop callback (one hop); coroutines get a task.
        self._is_async = inspect.iscoroutinefunction(handler)
        self._wake = asyncio.Event()
        self._task = node.spawn(self._dispatch(), name=f"sub:{key_expr}") if self._is_async else None
        # Per key: samples that arrived (lock-free tallies) and those the queue policy discarded (under _lock).
        self._arrived: dict[str, Tally] = {}
        self.dropped: collections.Counter[str] = collections.Counter()
        # Keys whose publisher declares another type or schema (shared/runtime/schemas.py): token -> why.
        self.refused: dict[str, dict[str, str]] = {}
        self.publishers: dict[str, set[str]] = {}  # key -> type tokens of its live publishers (any type)
        # key -> [count an arrival, take(payload) -> message or None]: one lookup per sample (_new_key)
        self._keys: dict[str, list] = {}
        self._types = (None if msgtype == "raw" else
                       node.session.liveliness().declare_subscriber(schemas.watch_expr(key_expr), self._on_type,
                                                                    history=True))
        self._exact = inbound.exact_key(key_expr)  # a single key: samples need not spell theirs out
        self._on_inline, self._on_sample = self._inline_callback(), self._queue_callback()
        self._sub = declare_subscriber(node.session, key_expr, self._on_inline if inline else self._on_sample, history)

    # Zenoh thread: a publisher's type token came or went.
    def _on_type(self, sample: zenoh.Sample) -> None:
        token = str(sample.key_expr)
        declared = schemas.parse_token(token)
        if declared is None:
            return
        expected = self.msgtype or keyreg.msgtype_of(declared.key)
        why = schemas.mismatch(declared, expected) if expected else None
        with self._lock:
            schemas.track(self.publishers, declared.key, token, gone=sample.kind == zenoh.SampleKind.DELETE)
            if sample.kind == zenoh.SampleKind.DELETE or why is None:
                gone = self.refused.get(declared.key, {})
                gone.pop(token, None)
                if not gone:
                    self.refused.pop(declared.key, None)
                return
            self.refused.setdefault(declared.key, {})[token] = why
        self._node.stats.count("type_mismatch_publisher", declared.key)
        self._node.log.error("refusing %s: %s", declared.key, why)

    def _refuse(self, key: str) -> bool:
        """A sample on a refused key: counted, dropped."""
        why = self.refused.get(key)
        if not why:
            return False
        self._node.reject(key, "type_mismatch", next(iter(why.values()), ""))
        return True

    # The Zenoh callbacks run per sample: what they use is bound once, when they are built.

    def _inline_callback(self) -> Callable[[zenoh.Sample], None]:
        """Zenoh thread, inline: decode, validate and handle at once."""
        keys, new_key, refused, refuse = self._keys, self._new_key, self.refused, self._refuse
        handler, wants_key, failed, exact = self._handler, self._wants_key, self._node.handler_failed, self._exact

        def on_inline(sample: zenoh.Sample) -> None:
            key = exact or str(sample.key_expr)
            arrive, take = keys.get(key) or new_key(key)
            arrive()
            if refused and refuse(key):
                return
            msg = take(sample.payload.to_bytes())
            if msg is not None:
                try:
                    handler(msg, key) if wants_key else handler(msg)
                except Exception as exc:  # a handler bug must not kill the subscription
                    failed(key, exc)
        return on_inline

    def _queue_callback(self) -> Callable[[zenoh.Sample], None]:
        """Zenoh thread: copy (and for a fifo, decode), queue by the policy, wake the loop once per batch."""
        keys, new_key, refused, refuse, exact = self._keys, self._new_key, self.refused, self._refuse, self._exact
        decoded, lock, queue_dropped = self._decoded, self._lock, self.dropped
        depth, fifo_policy, count = self.policy.depth, self.policy.kind == "fifo", self._node.stats.count
        wake, call_soon = self._wake.set if self._is_async else self._drain, self._loop.call_soon_threadsafe

        def on_sample(sample: zenoh.Sample) -> None:
            key = exact or str(sample.key_expr)
            arrive, take = keys.get(key) or new_key(key)
            arrive()
            payload = sample.payload.to_bytes()  # a copy now: a shared-memory buffer goes back to its pool at once
            if refused and refuse(key):
                return
            item = take(payload) if decoded else payload
            if item is None:  # rejected on arrival (counted by take)
                return
            with lock:
                queue = self._queue  # _drain swaps in a new queue
                if len(queue) >= depth:
                    if fifo_policy:
                        queue_dropped[key] += 1  # the newest is refused
                        count("queue_overflow")  # the recorder reports this total
                        return
                    queue_dropped[queue[0][0]] += 1  # keep-latest: the oldest gives way
                queue.append((key, item))
                if self._scheduled:
                    return
                self._scheduled = True
            try:
                call_soon(wake)
            except RuntimeError:  # loop closed during shutdown
                pass
        return on_sample

    def _drain(self) -> None:
        lock, handler, wants_key, failed = self._lock, self._handler, self._wants_key, self._node.handler_failed
        while True:
            with lock:
                if not self._queue:
                    self._scheduled = False
                    return
                if self._whole_batches:  # what is queued now, at once: nothing in it could still give way
                    batch, self._queue = self._queue, collections.deque(maxlen=self._queue.maxlen)
                else:  # keep-latest: one at a time, newer samples push out older ones meanwhile
                    batch = (self._queue.popleft(),)
            if self._decoded:
                for key, msg in batch:
                    try:
                        handler(msg, key) if wants_key else handler(msg)
                    except Exception as exc:  # a handler bug must not kill the subscription
                        failed(key, exc)
                continue
            keys = self._keys
            for key, payload in batch:
                msg = keys[key][1](payload)
                if msg is not None:
                    try:
                        handler(msg, key) if wants_key else handler(msg)
                    except Exception as exc:  # a handler bug must not kill the subscription
                        failed(key, exc)

    def _new_key(self, key: str) -> list:
        """The entry of a key heard for the first time; its decoder is built on its first sample
        that is not refused (a refused key gets no received meter)."""
        with self._lock:
            if key not in self._keys:
                tally = self._arrived[key] = Tally()
                self._keys[key] = [tally.add, functools.partial(self._first_take, key)]
            return self._keys[key]

    def _first_take(self, key: str, payload: bytes) -> Any:
        take = self._keys[key][1] = self._taker(key)
        return take(payload)

    def _taker(self, key: str) -> Callable[[bytes], Any]:
        msgtype = self.msgtype or keyreg.msgtype_of(key) or ""
        return inbound.taker(key, msgtype, self._node.stats.received_meter(key).tick, self._node.clock,
                             self._node.reject)

    async def _dispatch(self) -> None:
        while True:
            await self._wake.wait()
            self._wake.clear()
            with self._lock:
                self._scheduled = False
            while True:
                with self._lock:
                    if not self._queue:
                        break
                    key, item = self._queue.popleft()
                await self._deliver(key, item)

    async def _deliver(self, key: str, item: Any) -> None:
        msg = item if self._decoded else self._keys[key][1](item)
        if msg is None:
            return
        try:
            await (self._handler(msg, key) if self._wants_key else self._handler(msg))
        except Exception as exc:  # a handler bug must not kill the subscription
            self._node.handler_failed(key, exc)

    def counts(self) -> tuple[dict[str, int], dict[str, int]]:
        """(arrived, dropped by the queue policy) per key, a consistent snapshot."""
        with self._lock:
            return {k: t.value for k, t in self._arrived.items()}, dict(self.dropped)

    def close(self) -> None:
        self._sub.undeclare()
        if self._types is not None:
            self._types.undeclare()
        if self._task is not None:
            self._task.cancel()


class Node:
    """One service instance: typed pub/sub, queryables, liveliness, health and the clock."""

    def __init__(self, service: str, instance: str, session: zenoh.Session, clock_mode: str = "wall",
                 log: logging.Logger | None = None, ports: Binding | None = None) -> None:
        self.service = service
        self.instance = instance
        self.ports = ports  # the instance's declared ports resolved to keys (shared/wiring.py)
        self.session = session
        self.loop = asyncio.get_running_loop()
        self.log = log or logging.getLogger("xm")
        self.clock = Clock(clock_mode)
        self.stats = Stats()
        self.started = time.monotonic()
        self.status = "starting"
        self.message = ""
        self.health_extra: Callable[[], dict] | None = None
        self.logs = RateLimitedLog(self.log, LOG_SUMMARY_S)
        self._subs: list[Subscription] = []
        self._tasks: set[asyncio.Task] = set()
        self._closers: list[Callable[[], None]] = []
        self.stopping = asyncio.Event()
        self._token = session.liveliness().declare_token(self.key("@alive"))
        self.queryable("@health", lambda _req: self.health(), raw_key=True)
        self.clock.on_jump(self._on_clock_jump)
        self.spawn(self._flush_logs(), name="log-summaries")
        if clock_mode == "sim":  # on Zenoh's thread: stamps are checked against the newest time (Clock.observe)
            self.subscribe("xm/clock", lambda msg: self.clock.observe(msgs.stamp_seconds(msg.clock), self.loop),
                           msgtype="rosgraph_msgs/msg/Clock", inline=True)

    def key(self, topic: str) -> str:
        return keyreg.service_key(self.service, self.instance, topic)

    def _on_clock_jump(self, old: float, new: float) -> None:
        # Loops on clock.ticks() rebase themselves; services with their own timing listen too.
        self.stats.count("clock_jumped_back")
        self.log.warning("clock jumped back: schedules restart on the new timeline",
                         extra=fields(old=round(old, 3), new=round(new, 3)))

    def reject(self, key: str, reason: str, detail: str) -> None:
        """Counts a message unfit for its key (per key and reason) and logs it, rate-limited."""
        self.stats.reject(key, reason)
        self.logs.warning(f"rejected:{reason}:{key}", "rejected message", key=key, reason=reason,
                          detail=detail[:200])

    def handler_failed(self, key: str, exc: Exception) -> None:
        self.stats.count("handler_error", key)
        self.logs.emit(logging.ERROR, f"handler:{key}:{type(exc).__name__}", "handler failed", exc_info=exc,
                       key=key, error=repr(exc)[:300])

    async def _flush_logs(self) -> None:
        while True:
            await asyncio.sleep(1.0)
            self.logs.flush()

    def spawn(self, coro: Awaitable, name: str | None = None) -> asyncio.Task:
        task = asyncio.ensure_future(coro)
        if name:
            task.set_name(name)
        self._tasks.add(task)
        task.add_done_callback(self._task_done)
        return task

    def _task_done(self, task: asyncio.Task) -> None:
        self._tasks.discard(task)
        if not task.cancelled() and task.exception() is not None:
            self.log.error("task %s crashed: %r", task.get_name(), task.exception(), exc_info=task.exception())
            self.stats.count("task_crash")
            self.set_status("error", f"task {task.get_name()} crashed: {task.exception()!r}")

    def publisher(self, topic_or_key: str, msgtype: str | None = None, block: bool = False,
                  cache_last: bool = False) -> Publisher:
        key = topic_or_key if topic_or_key.startswith("xm/") else self.key(topic_or_key)
        msgtype = msgtype or keyreg.msgtype_of(key)
        if msgtype is None:
            raise ValueError(f"key {key} is declared by no services/*/ports.py; declare it or pass msgtype")
        return Publisher(self, key, msgtype, block, cache_last)

    def subscribe(self, key_expr: str, handler: Callable[..., Any], policy: QueuePolicy | None = None,
                  msgtype: str | None = None, inline: bool = False, history: bool = False) -> Subscription:
        """Handler gets ``(msg)`` or ``(msg, key)``; msgtype defaults to the registry's; "raw" gives bytes.
        ``inline``: the handler runs on Zenoh's thread as each sample arrives (module docstring);
        ``history``: first the latest sample of each state output (``on_change`` ports) it matches."""
        sub = Subscription(self, key_expr, msgtype, handler, policy or latest(1), inline, history)
        self._subs.append(sub)
        self._closers.append(sub.close)
        return sub

    def input(self, port: str, handler: Callable[..., Any]) -> list[Subscription]:
        """Subscribe declared input ``port`` (services/<name>/ports.py) with its type and queue policy."""
        bound = self._binding().input(port)
        return [self.subscribe(expr, handler, bound.queue, bound.msgtype) for expr in bound.key_exprs]

    def output(self, port: str, each: str = "") -> Publisher:
        """Publisher of declared output ``port``; ``each`` picks one key of a fanned-out port (a camera)."""
        bound = self._binding().output(port)
        if each not in bound.keys:
            raise KeyError(f"output {port!r} has no key for {each!r} (it has: {', '.join(bound.keys)})")
        return self.publisher(bound.keys[each], bound.msgtype, cache_last=bound.on_change)

    def _binding(self) -> Binding:
        if self.ports is None:
            raise RuntimeError(f"{self.service}/{self.instance}: node has no port binding (shared/wiring.bind)")
        return self.ports

    def queryable(self, name: str, handler: Callable[[dict], Any], raw_key: bool = False) -> None:
        """``xm/<service>/<instance>/<name>``; JSON in (may be empty), JSON out. Handler may be async."""
        key = self.key(name if raw_key or name.startswith("@") else f"@cmd/{name}")

        def on_query(query: zenoh.Query) -> None:
            payload = query.payload.to_bytes() if query.payload is not None else b""
            self.loop.call_soon_threadsafe(lambda: self.spawn(self._answer(query, key, payload, handler)))

        q = self.session.declare_queryable(key, on_query)
        self._closers.append(q.undeclare)

    async def _answer(self, query: zenoh.Query, key: str, payload: bytes, handler: Callable) -> None:
        try:
            request = json.loads(payload) if payload else {}
            if not isinstance(request, dict):
                raise ValueError("request must be a JSON object")
            reply = handler(request)
            if inspect.isawaitable(reply):
                reply = await reply
        except Exception as exc:
            self.stats.count("bad_request", key)
            reply = {"ok": False, "error": f"{type(exc).__name__}: {exc}"}
        try:
            query.reply(key, json.dumps(reply, default=_json_default))
        finally:
            query.drop()

    def set_status(self, status: str, message: str = "") -> None:
        if (status, message) != (self.status, self.message):  # a flapping status: a line, then summaries
            self.logs.emit(logging.INFO, f"status:{status}", f"status {status}", **({"message": message} if message
                                                                                  else {}))
        self.status, self.message = status, message

    def health(self) -> dict:
        now = time.monotonic()
        published, received, errors, rejected = self.stats.snapshot()
        report = {
            "service": self.service,
            "instance": self.instance,
            "pid": os.getpid(),
            "status": self.status,
            "message": self.message,
            "uptime_s": round(now - self.started, 3),
            "clock": self.clock.now(),
            "published_hz": {k: round(m.rate(now), 2) for k, m in published.items()},
            "published": {k: m.count for k, m in published.items()},
            "received_hz": {k: round(m.rate(now), 2) for k, m in received.items()},
            "errors": errors,
            "rejected": rejected,
            **self._queue_counts(),
            "clock_jumps": self.clock.jumps,
            "shm": shm.POOL.report(),  # the process's shared-memory pool: puts, and copies made instead
        }
        if self.health_extra is not None:
            report.update(self.health_extra())
        return report

    def _queue_counts(self) -> dict[str, dict[str, int]]:
        """Per key: samples that arrived, and those the subscriptions' queue policies discarded
        (arrived = handled + rejected + dropped, once the queues are drained)."""
        arrived: collections.Counter[str] = collections.Counter()
        dropped: collections.Counter[str] = collections.Counter()
        for sub in self._subs:
            a, d = sub.counts()
            arrived.update(a)
            dropped.update(d)
        return {"arrived": dict(arrived), "dropped": dict(dropped)}

    async def close(self) -> None:
        for close in reversed(self._closers):
            try:
                close()
            except Exception:  # undeclare after the session died is harmless
                pass
        for task in list(self._tasks):
            task.cancel()
        await asyncio.gather(*self._tasks, return_exceptions=True)
        try:
            self._token.undeclare()
        except Exception:
            pass


def _arity(func: Callable) -> int:
    try:
        return len(inspect.signature(func).parameters)
    except (TypeError, ValueError):
        return 1


def _json_default(obj: Any) -> Any:
    if hasattr(obj, "tolist"):
        return obj.tolist()
    return str(obj)
