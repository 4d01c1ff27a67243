"""Link shaping with ``tc``: capability detection, rate limits, cuts and restores.

The kernels this runs on may lack ``netem`` (and ``prio``, ``sfq``, filters); ``tbf``,
``htb`` and ``bfifo`` are widely present. So we detect what the kernel offers on the real
interface and choose:

- rate: ``tbf`` (token bucket; change the rate live with ``tc qdisc change``), else ``htb``
  with one default class, else ``netem rate``;
- cut: ``bfifo limit 0`` (every packet dropped silently, like a radio out of range), else
  ``netem loss 100%``.

Commands are built by pure functions (unit-tested) and run through an :data:`Exec` that is
``docker exec ROUTER`` for the e2e router or ``ip netns exec NS`` in tests. Shaping applies to
the *egress* of one interface: shape both directions of a link by shaping each side's egress.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass

from fleetctl.deploy.dockercli import Completed
from fleetctl.errors import EnvironmentMissing, FleetError

Exec = Callable[[Sequence[str]], Completed]

# tbf needs a bucket of at least one timer tick of traffic (rate / HZ; HZ may be 250), or it
# cannot reach its rate. 1/250 s of traffic, and never below 16 KB (a few full frames).
_MIN_BURST_BYTES = 16 * 1024
_TICKS_PER_S = 250


@dataclass(frozen=True)
class Capabilities:
    """Which qdiscs the kernel accepts on one interface."""

    netem: bool
    tbf: bool
    htb: bool
    bfifo: bool

    @property
    def rate_method(self) -> str:
        """``tbf``, ``htb`` or ``netem``: how rates are shaped.

        Raises:
            EnvironmentMissing: none of them works.
        """
        for name in ("tbf", "htb", "netem"):
            if getattr(self, name):
                return name
        raise EnvironmentMissing("tc: no rate-limiting qdisc (tbf, htb or netem) is available")

    @property
    def cut_method(self) -> str:
        """``bfifo-limit-0`` or ``netem-loss-100``: how a link is cut.

        Raises:
            EnvironmentMissing: neither works.
        """
        if self.bfifo:
            return "bfifo-limit-0"
        if self.netem:
            return "netem-loss-100"
        raise EnvironmentMissing("tc: neither bfifo nor netem is available to cut a link")

    def describe(self) -> str:
        """One line for reports, e.g. ``netem: no; rate: tbf; cut: bfifo-limit-0``."""
        return (
            f"netem: {'yes' if self.netem else 'no'}; rate: {self.rate_method}; "
            f"cut: {self.cut_method}"
        )


@dataclass(frozen=True)
class RateSpec:
    """A shaped link direction.

    Attributes:
        rate_bit_s: Link rate in bits per second.
        queue_latency_ms: Longest a packet may wait in the shaper's queue (tbf ``latency``);
            it sets the bottleneck buffer, rate * latency bytes.
    """

    rate_bit_s: int
    queue_latency_ms: int = 200

    def __post_init__(self) -> None:
        if self.rate_bit_s <= 0:
            raise FleetError(f"rate_bit_s must be positive, got {self.rate_bit_s}")
        if self.queue_latency_ms <= 0:
            raise FleetError(f"queue_latency_ms must be positive, got {self.queue_latency_ms}")

    @property
    def burst_bytes(self) -> int:
        """tbf bucket size in bytes (see ``_MIN_BURST_BYTES``)."""
        return max(_MIN_BURST_BYTES, self.rate_bit_s // 8 // _TICKS_PER_S)


def mbit(value: float) -> int:
    """Megabits per second to bits per second."""
    return int(value * 1_000_000)


def probe_argvs(dev: str) -> dict[str, list[str]]:
    """The ``tc qdisc replace`` command that proves each qdisc kind works on *dev*."""
    root = ["tc", "qdisc", "replace", "dev", dev, "root"]
    return {
        "netem": [*root, "netem", "delay", "0ms"],
        "tbf": [*root, "tbf", "rate", "100mbit", "burst", "64kb", "latency", "50ms"],
        "htb": [*root, "handle", "1:", "htb", "default", "1"],
        "bfifo": [*root, "bfifo", "limit", "100000"],
    }


def clear_argv(dev: str) -> list[str]:
    """Remove the root qdisc of *dev* (back to the kernel default)."""
    return ["tc", "qdisc", "del", "dev", dev, "root"]


def rate_argvs(dev: str, spec: RateSpec, method: str, *, live: bool) -> list[list[str]]:
    """Commands that shape *dev* to *spec* with *method* (``tbf``, ``htb`` or ``netem``).

    Args:
        dev: Interface name.
        spec: Rate and queue.
        method: From :attr:`Capabilities.rate_method`.
        live: The same method is already installed: change it in place (no packet loss,
            no queue flush) instead of replacing the qdisc.

    Raises:
        FleetError: unknown method.
    """
    op = "change" if live else "replace"
    rate = f"{spec.rate_bit_s}bit"
    if method == "tbf":
        return [["tc", "qdisc", op, "dev", dev, "root", "tbf", "rate", rate,
                 "burst", str(spec.burst_bytes), "latency", f"{spec.queue_latency_ms}ms"]]
    if method == "htb":
        cmds = [] if live else [["tc", "qdisc", "replace", "dev", dev, "root", "handle", "1:",
                                 "htb", "default", "1"]]
        cls_op = "change" if live else "replace"
        cmds.append(["tc", "class", cls_op, "dev", dev, "parent", "1:", "classid", "1:1", "htb",
                     "rate", rate, "ceil", rate, "burst", str(spec.burst_bytes)])
        return cmds
    if method == "netem":
        limit = max(100, spec.rate_bit_s // 8 * spec.queue_latency_ms // 1000 // 1500)
        return [["tc", "qdisc", op, "dev", dev, "root", "netem", "rate", rate,
                 "limit", str(limit)]]
    raise FleetError(f"unknown rate method {method!r}")


def cut_argv(dev: str, method: str) -> list[str]:
    """Command that drops every packet leaving *dev* (``bfifo-limit-0`` or ``netem-loss-100``).

    Raises:
        FleetError: unknown method.
    """
    if method == "bfifo-limit-0":
        return ["tc", "qdisc", "replace", "dev", dev, "root", "bfifo", "limit", "0"]
    if method == "netem-loss-100":
        return ["tc", "qdisc", "replace", "dev", dev, "root", "netem", "loss", "100%"]
    raise FleetError(f"unknown cut method {method!r}")


def detect(run: Exec, dev: str) -> Capabilities:
    """Try each qdisc kind on *dev*, leaving *dev* with its default qdisc.

    Run it before traffic matters: it replaces the root qdisc for a moment.
    """
    found = {name: run(argv).returncode == 0 for name, argv in probe_argvs(dev).items()}
    run(clear_argv(dev))
    return Capabilities(**found)


class LinkShaper:
    """Shapes the egress of one interface and remembers its state to cut and restore.

    Args:
        run: Runs a command where the interface lives (router container, namespace).
        dev: Interface name.
        caps: From :func:`detect` on the same interface.
    """

    def __init__(self, run: Exec, dev: str, caps: Capabilities) -> None:
        self._run = run
        self.dev = dev
        self.caps = caps
        self.rate: RateSpec | None = None
        self._installed: str | None = None  # method now at the root, None = kernel default
        self.commands: list[list[str]] = []  # every command run, for the report

    def _do(self, argv: list[str]) -> None:
        self.commands.append(argv)
        res = self._run(argv)
        if res.returncode != 0:
            raise FleetError(f"{' '.join(argv)} failed: {(res.stderr or res.stdout).strip()}")

    def set_rate(self, spec: RateSpec) -> None:
        """Shape to *spec*; changes the rate in place when already rate-shaped."""
        method = self.caps.rate_method
        for argv in rate_argvs(self.dev, spec, method, live=self._installed == method):
            self._do(argv)
        self.rate = spec
        self._installed = method

    def cut(self) -> None:
        """Drop every packet leaving the interface until :meth:`restore`."""
        method = self.caps.cut_method
        self._do(cut_argv(self.dev, method))
        self._installed = method

    def restore(self) -> None:
        """Undo a cut: back to the last rate, or to no shaping."""
        if self.rate is not None:
            spec, self._installed = self.rate, None
            self.set_rate(spec)
        else:
            self.clear()

    def clear(self) -> None:
        """Remove all shaping from the interface."""
        if self._installed is not None:
            self._do(clear_argv(self.dev))
        self._installed = None
        self.rate = None
