"""Zenoh side of actuatord: publishers fed from a queue by their own thread (a control loop in
real time never waits on the network, nor serialises; one on drive time publishes in turns,
see TURN_MESSAGES), and the queryables for parameters and the reference and weights of every
joint."""

import collections
import json
import logging
import threading
import time
from collections.abc import Callable, Iterable, Sequence

import zenoh
from google.protobuf.message import Message

from controller.messages import VIEW_CLASSES, Encoded, EncodedJointView, JointStates
from controller.requests import Body, RequestHandler
from protocol import telemetry as schema

log = logging.getLogger(__name__)

EXPRESS_TOPICS = ("state", "command", "fault")  # latency matters more than batching for these
# rare, and the one message a watcher must not miss: it waits out congestion (in the publisher
# thread; the loop only appends to the queue) where the others are dropped by Zenoh
NEVER_DROPPED = ("fault",)
QUEUE_DEPTH = 4096
_FAULT = schema.message_class("Fault")
# s between the publisher thread's passes over the queue. The loop only appends to a deque:
# no lock, no wake-up of another thread per message (in lock-step each wake-up handed the
# interpreter lock back and forth three times a cycle); telemetry waits at most this long.
DRAIN_PERIOD = 1e-3
# A loop on drive time (lock-step) never sleeps, so the thread's passes ran beside it, and
# each of Zenoh's puts releases the interpreter's lock: the loop took it, and the thread
# waited for the loop's next release (each compiled call releases it) to publish the next
# message, two thread switches and a wait a message, three or four messages a cycle (one
# joint: 70-90 us a cycle against 45-50 with nothing published). Such a loop takes turns
# instead (`take_turn`): from TURN_MESSAGES queued, or TURN_PERIOD after the last turn (a
# robot's one message a cycle, its cycles slower), what is queued is published in the loop's
# own thread, whose time is drive time's anyway. Handing each turn to the thread while the
# loop waited cost one joint 8-10 us a cycle more (53-61 us against 42-50 a cycle, 12 000
# cycles, alternating runs): the hand-overs and the messages' cache lines crossing cores. A
# put that may block (a fault's, which waits out congestion) is still the thread's: a turn
# that meets one hands it and the rest of the queue over and waits at most TURN_TIMEOUT, so
# drive time is held up no longer. From the loop's first look the thread's own passes stop
# (else they kept the queue short of a turn, and ran beside the loop); they resume
# TURN_LAPSE after its last look.
TURN_MESSAGES = 256
TURN_PERIOD = 0.02  # s
TURN_TIMEOUT = 0.1  # s
TURN_LAPSE = 0.1  # s


class TelemetryPublisher:
    """Publishes the loop's telemetry messages (a subscriber of the loop); serialisation happens
    in the publisher thread (in the loop's own turns on drive time). When the queue is full,
    messages are dropped and counted, never waited for."""

    def __init__(self, session: zenoh.Session, prefix: str = schema.DEFAULT_PREFIX,
                 topics: Iterable[str] = tuple(schema.topics(1)),
                 ros2_domain: int | None = None):
        """`topics`: the keys under the prefix to publish (`schema.topics(joints)`: one
        joint's view by default). `ros2_domain`: also publish `/joint_states` as rmw_zenoh
        does in that ROS domain (a single joint is named by the prefix's last segment, e.g.
        `elbow`)."""
        self.session = session
        self.prefix = prefix
        self.dropped = 0
        self._queue: collections.deque = collections.deque()
        self._closing = threading.Event()
        # a turn (`take_turn`): the loop releases `_go` and waits on `_done`, which the thread
        # releases once it has published the queue; plain locks (a Condition's wait and
        # notify are Python code, under the interpreter's lock the turn is to free)
        self._go, self._done = threading.Lock(), threading.Lock()
        self._go.acquire()
        self._done.acquire()
        self._turn_pending = False  # a turn given whose end the loop has not seen yet
        # one drainer at a time (the loop's turn, the thread's pass): the messages keep
        # their order
        self._draining = threading.Lock()
        self._looks = 0  # `take_turn`'s calls: while they grow, the thread waits for turns
        self.in_turns = False  # the thread publishes in turns only (for a look from outside)
        self.turns = 0  # given by a loop on drive time
        self._turn_at = 0.0  # time.monotonic() of the last
        self._publishers = {
            topic: session.declare_publisher(
                schema.key_expr(prefix, topic), encoding=zenoh.Encoding.APPLICATION_PROTOBUF,
                congestion_control=(zenoh.CongestionControl.BLOCK if topic in NEVER_DROPPED
                                    else zenoh.CongestionControl.DROP),
                express=topic in EXPRESS_TOPICS)
            for topic in topics}
        # each message class's publisher's put (`_drain`)
        self._puts = {schema.message_class(schema.TOPICS[topic]): publisher.put
                      for topic, publisher in self._publishers.items()}
        # a one-joint view's (`EncodedJointView`) parts' puts, in its order (None: not a topic
        # published here)
        self._view_puts = tuple(self._puts.get(kind) for kind in VIEW_CLASSES)
        self._queryables: list = []
        # dashboards watch this token to tell a vanished actuatord from a quiet one
        self._alive = session.liveliness().declare_token(
            schema.key_expr(prefix, schema.LIVELINESS))
        # audit lines must not be lost in a burst of telemetry: blocking (they are put from
        # the queryables' threads, never the loop's) and in a queue of their own priority
        self._audit = session.declare_publisher(
            schema.key_expr(prefix, schema.AUDIT), encoding=zenoh.Encoding.APPLICATION_JSON,
            congestion_control=zenoh.CongestionControl.BLOCK,
            priority=zenoh.Priority.INTERACTIVE_HIGH)
        self._ros2 = None
        if ros2_domain is not None:  # rosbags' type store is loaded only for it
            from controller.ros2 import JointStatePublisher

            joint = prefix.rstrip("/").rsplit("/", 1)[-1]
            self._ros2 = JointStatePublisher(session, ros2_domain, joint)
        self._thread = threading.Thread(target=self._run, name="telemetry", daemon=True)
        self._thread.start()

    def publish(self, message: "Message | EncodedJointView | Encoded") -> None:
        """Queue a message, or a one-joint view or plan as bytes (a wire subscriber of the loop),
        for the publisher thread. A full queue (a lock-step loop makes
        messages far faster than Zenoh takes them) drops it and counts it, except a fault:
        faults are rare and are what a user must see, so they always join the queue (a
        refused request's fault went missing this way in lock-step runs)."""
        if len(self._queue) < QUEUE_DEPTH or type(message) is _FAULT:
            self._queue.append(message)
        else:
            self.dropped += 1

    def publish_audit(self, line: str) -> None:
        """Audit lines (bounded JSON, see controller.requests) are rare and must not be
        dropped: published directly."""
        self._audit.put(line)
        log.info("audit: %s", line)

    def serve_json(self, name: str, answer: Callable[[Body], dict]) -> None:
        """A queryable at {prefix}/{name} that replies with answer(body) as JSON. The body is
        handed over as its size and a way to read it: Zenoh knows the size of what arrived
        without copying it, so an oversized body is refused without being read."""
        def on_query(query: zenoh.Query) -> None:
            payload = query.payload
            body = (Body(0, bytes) if payload is None else
                    Body(len(payload), payload.to_bytes))
            try:
                reply = json.dumps(answer(body))
            except Exception as exc:  # answer() refuses cleanly itself; this is the last net
                log.error("query on %s failed: %s", name, type(exc).__name__)
                reply = json.dumps({"ok": False, "reason": "internal error"})
            try:
                query.reply(query.key_expr, reply, encoding=zenoh.Encoding.APPLICATION_JSON)
            except Exception as exc:  # the querier may be gone
                log.warning("reply on %s not sent: %s", name, exc)

        self._queryables.append(
            self.session.declare_queryable(schema.key_expr(self.prefix, name), on_query))

    def serve_requests(self, handlers: Sequence[RequestHandler]) -> None:
        """Every joint's reference and weights queryables, {prefix}/joints/{name}/reference
        and .../weights; a robot of one joint also keeps its own {prefix}/reference and
        {prefix}/weights."""
        for handler in handlers:
            self.serve_json(schema.joint_key(handler.name, schema.REFERENCE),
                            handler.set_reference)
            self.serve_json(schema.joint_key(handler.name, schema.WEIGHTS), handler.set_weights)
        if len(handlers) == 1:
            self.serve_json(schema.REFERENCE, handlers[0].set_reference)
            self.serve_json(schema.WEIGHTS, handlers[0].set_weights)

    def take_turn(self) -> None:
        """From a loop on drive time (lock-step), once a cycle: with TURN_MESSAGES or more
        queued, they are published now, in this thread; from a put that may block on, by the
        publisher thread while the loop waits (see TURN_MESSAGES for why). Never from a loop
        on the wall clock: it would wait on the network."""
        self._looks += 1
        queued = len(self._queue)
        if queued < TURN_MESSAGES and not (
                queued and time.monotonic() - self._turn_at >= TURN_PERIOD):
            return
        if self._turn_pending:  # the last turn outlasted TURN_TIMEOUT: over by now?
            if not self._done.acquire(blocking=False):
                return
            self._turn_pending = False
        self._turn_at = time.monotonic()
        self.turns += 1
        if self._drain(until_blocking=True):
            return
        self._turn_pending = True
        self._go.release()
        if self._done.acquire(timeout=TURN_TIMEOUT):
            self._turn_pending = False

    def _run(self) -> None:
        # between turns a plain sleep, not `Event.wait`'s timeout: each wake-up of a timed
        # Condition cost 60 us of CPU here against 40 (a thousand a second in real time), and
        # `close` waits one period at most (TURN_LAPSE while turns come)
        closing, go, done = self._closing, self._go, self._done
        looks = 0
        while not closing.is_set():
            if self._looks != looks:  # a loop on drive time gives turns: wait for the next
                looks = self._looks
                self.in_turns = True
                if go.acquire(timeout=TURN_LAPSE):
                    self._drain()
                    done.release()
                continue
            self.in_turns = False
            time.sleep(DRAIN_PERIOD)
            turn = go.acquire(blocking=False)  # the first turn, given during the sleep
            self._drain()
            if turn:
                done.release()
        self._drain()

    def _drain(self, until_blocking: bool = False) -> bool:
        """Publish what is queued, in order; `until_blocking`: stop before a message whose put
        may block (left first in the queue). Whether the queue was emptied."""
        # every message is this loop's Python while holding the interpreter's lock: one
        # look-up of its publisher's put by its class
        queue, puts, view_puts, ros2 = self._queue, self._puts, self._view_puts, self._ros2
        popleft = queue.popleft
        with self._draining:
            while queue:
                message = popleft()
                kind = type(message)
                if until_blocking and kind is _FAULT:
                    queue.appendleft(message)
                    return False
                try:
                    if kind is Encoded:  # one message's bytes
                        puts[message.kind](message.data)
                        if ros2 is not None and message.kind is JointStates:
                            ros2.publish(message.decoded())  # parsed here, off the loop
                        continue
                    if kind is EncodedJointView:  # three messages' bytes, cut apart
                        data, start = message.data, 0
                        for put, end in zip(view_puts, message.ends, strict=True):
                            if put is not None:
                                put(data[start:end])
                            start = end
                        if ros2 is not None:
                            ros2.publish(message.state())
                        continue
                    puts[kind](message.SerializeToString())
                    if ros2 is not None:
                        ros2.publish(message)
                except Exception as exc:  # one bad message must not stop the telemetry
                    log.error("publishing %s failed: %r", kind.__name__, exc)
        return True

    def close(self) -> None:
        """Flush what is queued, then undeclare everything. A thread waiting for a turn is
        woken at once: it waited out TURN_LAPSE, and every lock-step run ended 0-0.1 s late
        (at random: 57 ms at the end of a 22 s run, 18 ms of a 2 s one)."""
        self._closing.set()
        try:
            self._go.release()  # a turn: the thread drains, then sees `_closing`
        except RuntimeError:  # a turn given and not yet taken: the thread wakes on that one
            pass
        self._thread.join(5)
        for entity in [*self._publishers.values(), *self._queryables, self._audit, self._alive]:
            entity.undeclare()
        if self._ros2 is not None:
            self._ros2.close()
