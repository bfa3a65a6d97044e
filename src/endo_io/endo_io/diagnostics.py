"""Per-node input health: drop bad messages, log one line, report honestly on /diagnostics.

Every endo3d node creates its subscriptions through :meth:`InputHealth.subscribe`
(or wraps its callbacks with :meth:`InputHealth.guard`). A callback that
raises is not allowed to take the node down: the message is dropped, the
cause (the exception class name) and its one-line message are logged
(throttled, so a stream of bad frames does not flood the console), and the
counters are published on ``/diagnostics`` as a
``diagnostic_msgs/DiagnosticArray`` once per period, where
``rqt_runtime_monitor`` and Foxglove's diagnostics panel show them.

What the status says (one ``DiagnosticStatus`` per :class:`InputHealth`):

* **level** WARN while any condition holds: a watched input was never seen
  or is stale (no message for ``input_stale_s``); a message was dropped, a
  frame lost in transport or the clock jumped within the last
  ``status_window_s``; a condition the node set (:meth:`set_problem`, e.g.
  a tracker that is not connected). Once none holds the level is OK again.
  The message names every condition ("ok" when there is none).
* **counters** (values, cumulative): ``received`` and ``received.<input>``
  (messages that arrived, decodable or not); ``processed`` (messages or
  frames that gave an output); ``dropped`` and ``dropped.<Cause>`` (dropped
  by the exception class that refused them); ``lost`` and ``lost.<input>``
  (frames missing from an image stream at its nominal rate: lost in
  transport, :class:`endo_io.sequence_gaps.SequenceGapCounter`);
  ``clock_jumps`` (state reset because time jumped); ``age_s.<input>``
  (seconds since the input's last message, or ``never``); ``skipped`` and
  ``skipped.<input>`` (stale frames passed over for a newer one, below);
  ``publishers.<input>`` (publishers its subscription matched now). An input
  never seen or stale is said with its publishers: "no publisher" (nobody
  publishes the topic here: a remap, another ``ROS_DOMAIN_ID`` or discovery
  range), "N publishers on the graph, none matched" (their QoS is
  incompatible with the subscription's), or "N publishers matched" (they
  send nothing, or the transport delivers nothing).

Subscriptions made by :meth:`subscribe` take the serialized message
(``raw=True``) and deserialize it inside the guard, so that a message whose
CDR cannot be decoded is counted (``dropped.UndecodableMessageError``) and
logged; a typed rclpy subscription loses it inside the middleware without a
trace. Images are decoded by :func:`endo_io.image.image_from_cdr`
(``decode=``): their pixels stay a view of the received bytes, with no
further copy.

Newest frame: a subscription made with ``newest=True`` (the frame a node
processes, through :data:`endo_io.qos.NEWEST_FRAME_QOS`) takes, before each
stale frame, the frames that wait behind it in the subscription and
processes the newest; the others are received and **skipped** (counted
under ``skipped``, not as dropped or lost: the node chose the present over
a backlog, nothing was wrong with them). The ``newest_frame`` parameter
(false) processes every frame in arrival order instead, as before.

Stale means older than ``frame_backlog_s`` (:data:`DEFAULT_FRAME_BACKLOG_S`)
since the middleware received it: a younger frame is processed in order,
even when newer ones wait behind it, so a stall of the node or of the
machine shorter than that delays a few frames instead of skipping them.
A stale frame makes the node skip to the newest. A second such skip within
:data:`BEHIND_HOLD_S` of the one before says the node is behind on average
(SFS at full resolution): from then until that long after its last skip of
a stale frame, every frame that has a newer one behind it is passed over
too, so the node works on the newest frame, not on one up to the limit old.
One stall alone costs only the frames it made stale. Frames wait in DDS
for up to ``frame_backlog_s`` plus one processing time: at the camera's
rate that must stay below :data:`endo_io.qos.NEWEST_FRAME_DEPTH` frames, or
DDS overwrites them (counted as lost): 0.1 s with a 30 ms step is 4 frames
at 30 fps, 8 at 60 fps.
With ``frame_backlog_s`` 0 every frame that has a newer one behind it is
skipped.

Taken by stamp: a subscription made with :meth:`InputHealth.subscribe_passive`
is never waited on by the executor (no wake-up, no callback per message); its
messages wait in the subscription's DDS history until the node takes them
(:meth:`PassiveInput.take`), e.g. the image and camera_info of a frame when
its depth arrives. They are counted as received when taken; messages the
history overwrote before anyone asked for them are not counted (they were
not needed: no frame came for them). While the node asks for it
(:meth:`PassiveInput.wake_on_arrival`), the executor wakes it at the input's
next message instead, which is delivered the same way, then the input's
``on_arrival`` runs: e.g. the poses, while a frame waits for its pose.

While the process shuts down (SIGINT in the middle of a callback), an
exception from a publisher whose context is gone is not a dropped message:
it is neither logged nor counted.
"""

from __future__ import annotations

import functools
import time
from collections import Counter, deque
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any, Protocol, TypeVar, cast

from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue
from rclpy.exceptions import InvalidHandle
from rclpy.node import Node
from rclpy.qos import QoSProfile
from rclpy.serialization import deserialize_message
from rclpy.subscription import Subscription

from endo_io.errors import ClockJumpError, Endo3dError, UndecodableMessageError
from endo_io.parameters import ParameterSpec
from endo_io.qos import reliable_qos
from endo_io.sequence_gaps import SequenceGapCounter
from endo_io.serialized_stamp import serialized_header_stamp_ns
from endo_io.stamp import stamp_to_ns
from endo_io.stamp_matching import StampMatcher
from endo_io.taking import OnDemandGroup, system_to_monotonic_ns, take_waiting

F = TypeVar("F", bound=Callable[..., Any])

DIAGNOSTICS_TOPIC = "/diagnostics"
#: Default of ``input_stale_s``: an input silent this long is stale (s).
DEFAULT_STALE_S = 2.0
#: Default of ``status_window_s``: a drop, loss or jump keeps WARN this long (s).
DEFAULT_WINDOW_S = 5.0
#: Default of ``frame_backlog_s``: the age (seconds since the middleware
#: received it) up to which a frame is processed in order though newer ones
#: wait. 0.1 s is three frames at 30 fps: longer than the stalls of the whole
#: machine seen in bench_graph's passes (in one, even the correction node
#: skipped 5 frames); it raised the end-to-end p99 at solve_scale 0.5 from
#: 75-88 to 101-120 ms with stalls (177 ms beside a foreign test suite) against
#: issue 15's 150 ms. (Limit + one frame's work) x rate must stay below
#: :data:`endo_io.qos.NEWEST_FRAME_DEPTH` (8): see the module docstring.
DEFAULT_FRAME_BACKLOG_S = 0.1
#: Two skips this close (seconds) say the input's node is behind on average;
#: it then takes the newest frame until this long after its last skip of a
#: stale frame (a
#: backlog kept in order would only add ``frame_backlog_s`` to every frame's
#: latency: SFS at full resolution, p50 196 against 67 ms in bench_graph,
#: session 15; holding after every single skip instead made a lone stall at
#: solve_scale 0.5 cost a second of skips: 7-12 against 0-5 per 60 s).
BEHIND_HOLD_S = 1.0
#: Events remembered per kind for the window's counts (memory bound).
_MAX_EVENTS = 10_000

#: The rows every node adds to its parameter table (see :mod:`endo_io.parameters`);
#: :class:`InputHealth` reads them at each status when given the node's parameters.
HEALTH_PARAMETERS: tuple[ParameterSpec, ...] = (
    ParameterSpec(
        "input_stale_s", DEFAULT_STALE_S,
        "diagnostics: an input without a message for this long is stale (WARN), seconds",
        range=(0.05, 3600.0),
    ),
    ParameterSpec(
        "newest_frame", True,
        "process only the newest waiting frame of the node's frame input and skip (count) the "
        "stale ones; false: every frame in arrival order",
    ),
    ParameterSpec(
        "frame_backlog_s", DEFAULT_FRAME_BACKLOG_S,
        "newest_frame: a frame received at most this long ago is not stale: it is processed in "
        "order though newer ones wait (a stall shorter than this delays frames instead of "
        "skipping them); 0: always the newest, seconds",
        range=(0.0, 0.25),
    ),
    ParameterSpec(
        "status_window_s", DEFAULT_WINDOW_S,
        "diagnostics: a drop, a lost frame or a clock jump keeps the status WARN this long, "
        "seconds",
        range=(0.0, 3600.0),
    ),
)


class Settings(Protocol):
    """What :class:`InputHealth` reads its settings from: the node's parameters, a dict."""

    def __getitem__(self, name: str) -> Any: ...


@dataclass
class _Input:
    """One watched input: what arrived and when."""

    received: int = 0
    last_arrival: float | None = None
    gaps: SequenceGapCounter | None = None
    subscription: Subscription | None = None  # the node's, when it made one for the input


def _age_ns(info: Any) -> float:
    """How long ago the middleware received a message, ns (inf when its info does not say)."""
    received = info.get("received_timestamp") if isinstance(info, dict) else None
    return time.time_ns() - received if received else float("inf")


@dataclass
class _Events:
    """Monotonic times of one kind of event, the newest last (bounded)."""

    times: deque[float] = field(default_factory=lambda: deque(maxlen=_MAX_EVENTS))
    last_text: str = ""

    def add(self, now: float, text: str, count: int = 1) -> None:
        self.times.extend([now] * min(count, _MAX_EVENTS))
        self.last_text = text

    def recent(self, now: float, window_s: float) -> int:
        while self.times and now - self.times[0] > window_s:
            self.times.popleft()
        return len(self.times)


class PassiveInput:
    """A subscription whose messages the node takes when it wants them (see the module doc).

    Made by :meth:`InputHealth.subscribe_passive`.

    Attributes:
        subscription: the rclpy subscription (raw; run by the executor only while
            :meth:`wake_on_arrival` is on; its callback, :meth:`arrived`, is also
            for messages given directly, as tests and offline drivers give them).
        name: the resolved topic name it is counted under.
    """

    def __init__(self, health: InputHealth, msg_type: Any, name: str,
                 callback: Callable[[Any, int], None], processed: bool,
                 decode: Callable[[bytes], Any] | None,
                 on_arrival: Callable[[], None] | None = None) -> None:
        self._health = health
        self._msg_type = msg_type
        self.name = name
        self._callback = callback
        self._processed = processed
        self._decode = decode
        self._on_arrival = on_arrival
        self.group = OnDemandGroup()
        self.subscription: Subscription | None = None

    def wake_on_arrival(self, wake: bool) -> None:
        """Whether the executor wakes the node at the input's next message (off at first).

        While on, each message that arrives is delivered as :meth:`take`
        delivers it (timed when the executor gives it), then ``on_arrival``
        runs. Applies from the executor's next wait.
        """
        self.group.waited = wake

    def arrived(self, data: Any) -> None:
        """A message the executor gave (or a test): :meth:`deliver`, then ``on_arrival``."""
        self.deliver(data)
        if self._on_arrival is not None:
            self._on_arrival()

    def take(self) -> int:
        """Deliver every message waiting in the subscription, oldest first; how many there were.

        Each goes through :meth:`deliver` with the time the middleware received it.
        """
        assert self.subscription is not None
        taken = take_waiting(self.subscription)
        for data, received_ns in taken:
            self.deliver(data, system_to_monotonic_ns(received_ns))
        return len(taken)

    def deliver(self, data: Any, arrival_ns: int | None = None) -> None:
        """Decode ``data`` (a message given as such is taken as it is), count it, call back.

        Guarded as :meth:`InputHealth.guard`: an undecodable message or a
        callback that raises drops that message only (counted and logged).

        Args:
            data: the serialized message, or the message.
            arrival_ns: when it arrived, ``time.monotonic_ns``'s clock (None: now).
        """
        self._health._call(self._decode_and_call, self._processed, data, arrival_ns)

    def _decode_and_call(self, data: Any, arrival_ns: int | None) -> None:
        msg = data if isinstance(data, self._msg_type) else self._health._decode(
            data, self._msg_type, self.name, self._decode)
        header = getattr(msg, "header", None)
        self._health.received(self.name, stamp_to_ns(header.stamp) if header is not None
                              else None)
        self._callback(msg, time.monotonic_ns() if arrival_ns is None else arrival_ns)


class InputHealth:
    """Counts what a node receives, outputs, drops and loses, and reports it.

    Args:
        node: the node that owns the counters; its name prefixes the status name.
        name: what is being monitored, e.g. ``"image input"``.
        period_s: publishing period of ``/diagnostics`` in seconds.
        log_throttle_s: minimum interval between two log lines of the same cause.
        stale_after_s: an input silent this long is stale; overridden by the
            ``input_stale_s`` entry of ``settings``.
        window_s: how long a drop, loss or jump keeps the level WARN;
            overridden by the ``status_window_s`` entry of ``settings``.
        settings: the node's parameters (:class:`endo_io.parameters.NodeParameters`
            or a dict); read at every status, so run-time changes apply.
        clock: the monotonic clock (seconds) that times arrivals, events and
            log throttling; ``time.monotonic`` (a test passes its own).
    """

    def __init__(
        self,
        node: Node,
        name: str = "input",
        period_s: float = 1.0,
        log_throttle_s: float = 1.0,
        *,
        stale_after_s: float = DEFAULT_STALE_S,
        window_s: float = DEFAULT_WINDOW_S,
        settings: Settings | None = None,
        clock: Callable[[], float] = time.monotonic,
    ) -> None:
        self._node = node
        self._clock = clock
        self._name = f"{node.get_name()}: {name}"
        self._log_throttle_s = log_throttle_s
        self._stale_after_s = stale_after_s
        self._window_s = window_s
        self._settings = settings
        self.processed = 0
        self.dropped: Counter[str] = Counter()
        self.skipped: Counter[str] = Counter()
        # per newest-frame input: until when (monotonic ns) it takes the newest frame
        self._behind_until: dict[str, int] = {}
        self._last_skip: dict[str, int] = {}  # when (monotonic ns) it last skipped a stale frame
        self.clock_jumps = 0
        self.last_error = ""
        self._inputs: dict[str, _Input] = {}
        self._events = {"dropped": _Events(), "lost": _Events(), "clock jump": _Events()}
        self._problems: dict[str, str] = {}
        self._refreshers: list[Callable[[], None]] = []
        self._last_log: dict[str, float] = {}
        self._extra: dict[str, str] = {}
        self._publisher = node.create_publisher(
            DiagnosticArray, DIAGNOSTICS_TOPIC, reliable_qos(10)
        )
        self._timer = node.create_timer(period_s, self.publish)

    # -- settings -------------------------------------------------------------------

    @property
    def stale_after_s(self) -> float:
        """Seconds without a message after which a watched input is stale."""
        return self._setting("input_stale_s", self._stale_after_s)

    @property
    def window_s(self) -> float:
        """Seconds a drop, a loss or a clock jump keeps the level WARN."""
        return self._setting("status_window_s", self._window_s)

    @property
    def newest_frame(self) -> bool:
        """Whether ``newest=True`` subscriptions skip stale frames (``newest_frame``)."""
        if self._settings is not None:
            try:
                return bool(self._settings["newest_frame"])
            except KeyError:
                pass
        return True

    @property
    def frame_backlog_ns(self) -> int:
        """Age past which a waiting frame is stale (``frame_backlog_s``), integer ns."""
        return round(self._setting("frame_backlog_s", DEFAULT_FRAME_BACKLOG_S) * 1e9)

    def _setting(self, key: str, default: float) -> float:
        if self._settings is not None:
            try:
                return float(self._settings[key])
            except KeyError:
                pass
        return default

    # -- inputs ---------------------------------------------------------------------

    def watch(self, input_name: str, *, gaps: bool = False) -> None:
        """Watch an input: WARN until its first message and whenever it is stale.

        ``gaps=True`` also counts frames missing from its stamps (image topics).
        """
        if input_name not in self._inputs:
            self._inputs[input_name] = _Input(gaps=SequenceGapCounter() if gaps else None)

    def unwatch(self, input_name: str) -> None:
        """Stop watching an input (a subscription that was replaced)."""
        self._inputs.pop(input_name, None)

    def received(self, input_name: str, stamp_ns: int | None = None) -> None:
        """Count one message that arrived on ``input_name`` (watched from now on).

        ``stamp_ns`` (its header stamp) feeds the gap count of an input
        watched with ``gaps=True``.
        """
        self.watch(input_name)
        entry = self._inputs[input_name]
        entry.received += 1
        entry.last_arrival = self._clock()
        if entry.gaps is not None and stamp_ns is not None:
            missing = entry.gaps.add(stamp_ns)
            if missing:
                self.lose(input_name, missing)

    def skip(self, input_name: str, count: int = 1) -> None:
        """Count ``count`` stale frames of ``input_name`` passed over for a newer one."""
        self.skipped[input_name] += count

    def lose(self, input_name: str, count: int) -> None:
        """Count ``count`` frames of ``input_name`` lost in transport (logged, throttled)."""
        total = self.lost_on(input_name)
        text = f"{count} frame(s) missing on {input_name} ({total} so far)"
        self._events["lost"].add(self._clock(), text, count)
        self._log(f"lost:{input_name}", "warning", f"lost in transport: {text}")

    def lost_on(self, input_name: str) -> int:
        """Frames of ``input_name`` counted as lost in transport so far."""
        entry = self._inputs.get(input_name)
        return 0 if entry is None or entry.gaps is None else entry.gaps.lost

    # -- outcomes -------------------------------------------------------------------

    def ok(self) -> None:
        """Count one message (or frame) processed to an output."""
        self.processed += 1

    def set_value(self, key: str, value: object) -> None:
        """Report an extra key/value (e.g. a latency figure) with the next status."""
        self._extra[key] = str(value)

    def drop(self, cause: str, message: str, *, expected: bool = False) -> None:
        """Count one dropped message under ``cause`` and log ``message`` (throttled).

        ``expected``: a condition of normal operation, not a fault (a frame
        before the pose stream's first pose, at every start and loop): counted
        and reported the same, logged as a warning (``<Cause> (N so far):
        <message>``) instead of an error.
        """
        self.dropped[cause] += 1
        self.last_error = f"{cause}: {message}"
        self._events["dropped"].add(self._clock(), self.last_error)
        total = self.dropped[cause]
        if expected:
            self._log(cause, "warning", f"{cause} ({total} so far): {message}")
        else:
            self._log(cause, "error", f"dropped message ({total} so far): {self.last_error}")

    def clock_jump(self, message: str) -> None:
        """Count one reset of the node's state because time jumped, and log ``message``."""
        self.clock_jumps += 1
        self._events["clock jump"].add(self._clock(), message)
        self._log("clock jump", "warning", f"clock jump ({self.clock_jumps} so far): {message}")

    def set_problem(self, key: str, message: str | None) -> None:
        """Hold the level at WARN with ``message`` while it is set; None clears it."""
        if message is None:
            self._problems.pop(key, None)
        else:
            self._problems[key] = message

    def watch_matching(self, matcher: StampMatcher[Any, Any], first: str, second: str) -> None:
        """WARN on /diagnostics, and log once, while ``matcher``'s two streams come unpaired.

        Args:
            matcher: the node's matcher of the two streams.
            first: its first stream's name (a topic), as the line names it.
            second: its second stream's name.
        """
        key = f"stamps of {first} and {second}"

        def refresh() -> None:
            line = matcher.mismatch(first, second)
            if line is not None and key not in self._problems:
                self._node.get_logger().warning(f"no frame: {line}")
            self.set_problem(key, line)

        self.on_refresh(refresh)

    def on_refresh(self, refresh: Callable[[], None]) -> None:
        """Call ``refresh()`` before each status is published (to copy a source's state)."""
        self._refreshers.append(refresh)

    def _log(self, key: str, level: str, text: str) -> None:
        now = self._clock()
        if now - self._last_log.get(key, -1e18) >= self._log_throttle_s:
            self._last_log[key] = now
            # rclpy fixes a call site's severity: one call per severity
            if level == "error":
                self._node.get_logger().error(text)
            else:
                self._node.get_logger().warning(text)

    # -- callbacks ------------------------------------------------------------------

    def guard(self, callback: F, *, input_name: str | None = None, processed: bool = True) -> F:
        """Wrap a callback so that any exception drops that message only.

        Named :class:`~endo_io.errors.Endo3dError` subclasses are expected bad
        input; any other exception is a bug, but a bug on one frame must not
        stop a node beside a surgery either, so it is counted the same way
        under its class name. A :class:`~endo_io.errors.ClockJumpError` is a
        reset, counted under ``clock_jumps``.

        Args:
            callback: the function to wrap.
            input_name: count each call as a message received on this input.
            processed: count a call that returns normally as processed; False
                for a callback that does not itself give an output (one half of
                a stamp pair) and calls :meth:`ok` where it does.
        """

        @functools.wraps(callback)
        def guarded(*args: Any, **kwargs: Any) -> Any:
            if input_name is not None:
                self.received(input_name)
            return self._call(callback, processed, *args, **kwargs)

        return guarded  # type: ignore[return-value]

    def _call(self, callback: Callable[..., Any], processed: bool, *args: Any,
              **kwargs: Any) -> Any:
        try:
            result = callback(*args, **kwargs)
        except ClockJumpError as error:
            self.clock_jump(str(error))
            return None
        except Exception as error:  # the node must keep running
            if not self._node.context.ok():
                return None  # shutting down: a publisher's context is gone, nothing was lost
            unexpected = not isinstance(error, Endo3dError)
            self.drop(type(error).__name__, f"unexpected: {error}" if unexpected else str(error))
            return None
        if processed:
            self.ok()
        return result

    def subscribe(
        self,
        msg_type: Any,
        topic: str,
        callback: Callable[[Any], None],
        qos: QoSProfile,
        *,
        processed: bool = True,
        gaps: bool = False,
        newest: bool = False,
        decode: Callable[[bytes], Any] | None = None,
    ) -> Subscription:
        """Subscribe ``callback`` to ``topic`` through the guard, decoding inside it.

        The input is watched under the resolved topic name (remaps applied).

        Args:
            msg_type: the message class (``sensor_msgs.msg.Image``, ...).
            topic: the topic name.
            callback: called with each decoded message.
            qos: the subscription's QoS.
            processed: as in :meth:`guard`.
            gaps: count frames missing from the header stamps (image topics).
            newest: before each stale message (older than
                ``frame_backlog_s``, or any while the node is behind: see
                the module's docstring), take the ones waiting behind it and
                process the newest; the others are counted as skipped (unless the
                ``newest_frame`` setting is false).
            decode: turns the serialized bytes into what ``callback`` takes
                (:func:`endo_io.image.image_from_cdr` for images: no copy of
                the pixels); rclpy's ``deserialize_message`` by default. Any
                exception it raises drops the message as undecodable.

        Returns:
            The rclpy subscription (raw: it delivers bytes to the guard).
        """
        name = self._node.resolve_topic_name(topic)
        self.watch(name, gaps=gaps)

        def decode_and_call(data: Any, info: Any) -> None:
            if newest and isinstance(data, bytes) and self.newest_frame:
                data = self._take_newest(subscription, msg_type, name, data, info)
            # a message given directly (tests, offline drivers) needs no decoding
            msg = data if isinstance(data, msg_type) else self._decode(data, msg_type, name,
                                                                          decode)
            header = getattr(msg, "header", None)
            self.received(name, stamp_to_ns(header.stamp) if header is not None else None)
            callback(msg)

        def guarded(data: Any, info: Any) -> Any:
            # two arguments: rclpy then passes the message's info (its receive time)
            return self._call(decode_and_call, processed, data, info)

        # rclpy's annotation names one-argument callbacks only; it inspects the
        # signature and passes (message, info) to a two-argument one
        subscription = self._node.create_subscription(
            msg_type, topic, cast(Callable[[Any], None], guarded), qos, raw=True)
        self._inputs[name].subscription = subscription
        return subscription

    def subscribe_passive(
        self,
        msg_type: Any,
        topic: str,
        callback: Callable[[Any, int], None],
        qos: QoSProfile,
        *,
        processed: bool = False,
        gaps: bool = False,
        decode: Callable[[bytes], Any] | None = None,
        on_arrival: Callable[[], None] | None = None,
    ) -> PassiveInput:
        """Subscribe to ``topic`` without a wake-up per message: the node takes them when it asks.

        The executor never waits on the subscription; its messages wait in its
        DDS history (``qos``'s depth: make it deep enough for the time until
        they are taken) until :meth:`PassiveInput.take` delivers them, each to
        ``callback(message, arrival_ns)`` through the guard.

        Args:
            msg_type: the message class.
            topic: the topic name.
            callback: called with each decoded message and when it arrived
                (``time.monotonic_ns``'s clock).
            qos: the subscription's QoS.
            processed: as in :meth:`guard`.
            gaps: count frames missing from the stamps of the messages taken.
            decode: as in :meth:`subscribe`.
            on_arrival: runs after each message the executor delivered while
                :meth:`PassiveInput.wake_on_arrival` was on (e.g. take the rest).

        Returns:
            The input, to take messages from.
        """
        name = self._node.resolve_topic_name(topic)
        self.watch(name, gaps=gaps)
        passive = PassiveInput(self, msg_type, name, callback, processed, decode, on_arrival)
        passive.subscription = self._node.create_subscription(
            msg_type, topic, passive.arrived, qos, raw=True, callback_group=passive.group)
        self._inputs[name].subscription = passive.subscription
        return passive

    def _take_newest(
        self, subscription: Subscription, msg_type: Any, name: str, data: bytes, info: Any
    ) -> bytes:
        """``data`` when it is not stale, else the newest serialized message waiting.

        The ones passed over are received and skipped. ``info`` is rclpy's
        message info of ``data`` (None: its age is unknown, so it is stale).
        """
        now = time.monotonic_ns()
        behind = now < self._behind_until.get(name, 0)
        # only a frame older than the limit says the node is behind; a young
        # one skipped because the node was already behind must not extend it
        # (frames that come in pairs would hold a fast node there for good)
        stale = _age_ns(info) > self.frame_backlog_ns
        if not behind and not stale:
            return data
        skipped = False
        while True:
            with subscription.handle:
                taken = subscription.handle.take_message(msg_type, True)
            if taken is None:
                break
            self.received(name, serialized_header_stamp_ns(data))
            self.skip(name)
            skipped = True
            data, info = taken
        if skipped and stale:
            # a second skip of a stale frame within the hold of the first: behind on average
            hold_ns = round(BEHIND_HOLD_S * 1e9)
            if now - self._last_skip.get(name, -hold_ns) < hold_ns:
                self._behind_until[name] = now + hold_ns
            self._last_skip[name] = now
        return data

    def _decode(self, data: bytes, msg_type: Any, name: str,
                decode: Callable[[bytes], Any] | None) -> Any:
        """Deserialize CDR ``data``; an undecodable message is received, then refused.

        Raises:
            UndecodableMessageError: one line naming the topic, the type and the cause.
        """
        try:
            if decode is not None:
                return decode(data)
            return deserialize_message(data, msg_type)
        except Exception as error:  # rclpy raises RMWError, or TypeError on junk
            self.received(name)
            first = str(error).splitlines()[0] if str(error) else type(error).__name__
            raise UndecodableMessageError(
                f"{len(data)} bytes on {name} do not decode as {msg_type.__name__}: {first}"
            ) from None

    # -- status ---------------------------------------------------------------------

    def problems(self) -> list[str]:
        """The conditions that make the level WARN now (empty: OK)."""
        now = self._clock()
        stale_s, window_s = self.stale_after_s, self.window_s
        found = []
        for name, entry in list(self._inputs.items()):
            if entry.last_arrival is None:
                found.append(f"no message yet on {name}{self._publishers_said(name, entry)}")
            elif now - entry.last_arrival > stale_s:
                found.append(f"{name} stale: nothing for {now - entry.last_arrival:.1f} s"
                             f"{self._publishers_said(name, entry)}")
        for kind, events in self._events.items():
            count = events.recent(now, window_s)
            if count:
                found.append(
                    f"{count} {kind} in the last {window_s:g} s (last: {events.last_text})"
                )
        found += list(self._problems.values())
        return found

    def _publishers(self, name: str, entry: _Input) -> tuple[int, int] | None:
        """The input's matched publishers and the topic's publishers on the graph, or None.

        None when the node made no subscription for it (or it is being destroyed).
        """
        if entry.subscription is None:
            return None
        try:
            return entry.subscription.get_publisher_count(), self._node.count_publishers(name)
        except (RuntimeError, InvalidHandle):  # rclpy's: the context or handle is gone
            return None

    def _publishers_said(self, name: str, entry: _Input) -> str:
        """Why a silent input may be silent, from its publishers ("" when unknown).

        Tells apart a topic nobody publishes (a remap, another domain or
        discovery range), one whose publishers' QoS this subscription cannot
        match (the graph has them, none matched), and one matched yet silent
        (the publisher sends nothing, or the transport delivers nothing).
        """
        counts = self._publishers(name, entry)
        if counts is None:
            return ""
        matched, on_graph = counts
        if matched:
            return f" ({matched} publisher{'s' * (matched != 1)} matched)"
        if on_graph:
            return (f" ({on_graph} publisher{'s' * (on_graph != 1)} on the graph, none matched:"
                    " incompatible QoS?)")
        return " (no publisher)"

    def status(self) -> DiagnosticStatus:
        """The current level, message and counters as one ``DiagnosticStatus``."""
        problems = self.problems()
        level = DiagnosticStatus.WARN if problems else DiagnosticStatus.OK
        message = "; ".join(problems) if problems else "ok"
        now = self._clock()
        inputs = sorted(self._inputs.items())
        dropped = sorted(self.dropped.items())
        pairs: list[tuple[str, object]] = [
            ("received", sum(entry.received for _, entry in inputs)),
            ("processed", self.processed),
            ("skipped", sum(self.skipped.values())),
            ("dropped", sum(count for _, count in dropped)),
            *((f"dropped.{cause}", count) for cause, count in dropped),
            ("lost", sum(self.lost_on(name) for name, _ in inputs)),
            ("clock_jumps", self.clock_jumps),
        ]
        for name, entry in inputs:
            age = "never" if entry.last_arrival is None else f"{now - entry.last_arrival:.2f}"
            pairs += [(f"received.{name}", entry.received), (f"age_s.{name}", age)]
            counts = self._publishers(name, entry)
            if counts is not None:
                pairs.append((f"publishers.{name}", counts[0]))
            if name in self.skipped:
                pairs.append((f"skipped.{name}", self.skipped[name]))
            if entry.gaps is not None:
                pairs.append((f"lost.{name}", entry.gaps.lost))
        if self.last_error:
            pairs.append(("last_error", self.last_error))
        values = [KeyValue(key=k, value=str(v)) for k, v in pairs]
        values += [KeyValue(key=k, value=v) for k, v in sorted(self._extra.items())]
        return DiagnosticStatus(
            level=level,
            name=self._name,
            message=message[:512],
            hardware_id=self._node.get_fully_qualified_name(),
            values=values,
        )

    def publish(self) -> None:
        """Refresh the node's conditions, then publish the current status on ``/diagnostics``."""
        for refresh in self._refreshers:
            try:
                refresh()
            except Exception as error:  # a refresh bug must not stop the timer
                self._log("refresh", "error", f"diagnostics refresh failed: {error!r}")
        array = DiagnosticArray()
        array.header.stamp = self._node.get_clock().now().to_msg()
        array.status = [self.status()]
        self._publisher.publish(array)
