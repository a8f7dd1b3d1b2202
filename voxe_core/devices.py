"""Where a stage runs and how much memory it took: device resolution and per-stage peak memory.

Every stage takes a ``device`` (``torch.device`` or a string such as ``"cuda:1"``).
:func:`resolve_device` turns it into a ``torch.device`` and refuses one this
machine cannot use *before* any work starts, so a job asking for CUDA on a
CPU-only worker fails at once with a message that says so, not after minutes
of work or with an error from deep inside a kernel.

:class:`PeakMemory` measures a stage's high-water mark: the CUDA caching
allocator's ``max_memory_allocated`` (reset when the stage starts) on a GPU,
the process's resident-set peak (``VmHWM``, reset through
``/proc/self/clear_refs`` where the kernel allows it) on the CPU. Stages put it
into their progress reports as ``info["peak_memory_gb"]`` (GiB, 2³⁰ bytes) and
``info["peak_memory_kind"]`` (``"cuda_allocated"``, ``"process_rss"`` or
``None`` where nothing can be measured).

Examples:
    >>> resolve_device("cpu")
    device(type='cpu')
    >>> resolve_device(torch.device("meta"))
    device(type='meta')
"""

from __future__ import annotations

from contextlib import ExitStack, contextmanager
from pathlib import Path

import torch

GIB = float(1 << 30)
_PROC_STATUS = Path("/proc/self/status")
_PROC_CLEAR_REFS = Path("/proc/self/clear_refs")


class DeviceUnavailableError(ValueError):
    """A stage was asked to run on a device this machine does not have."""


def default_device() -> torch.device:
    """CUDA when this machine has it, else the CPU."""
    return torch.device("cuda" if torch.cuda.is_available() else "cpu")


def resolve_device(device: torch.device | str | None = None) -> torch.device:
    """``device`` as a ``torch.device`` (None: :func:`default_device`); DeviceUnavailableError when unusable.

    ``"cuda"`` without an index stays index-less (the current CUDA device). The
    check is cheap and runs before a stage touches data.
    """
    if device is None or device == "auto":
        return default_device()
    try:
        resolved = torch.device(device)
    except (RuntimeError, TypeError) as exc:
        raise DeviceUnavailableError(f"unknown device {device!r}: {exc}") from None
    if resolved.type == "cuda":
        if not torch.cuda.is_available():
            raise DeviceUnavailableError(
                f"device {str(resolved)!r} asked for, but this machine has no usable CUDA device "
                f"(torch {torch.__version__}, torch.cuda.is_available() is False); use device 'cpu'"
            )
        count = torch.cuda.device_count()
        if resolved.index is not None and resolved.index >= count:
            raise DeviceUnavailableError(f"device {str(resolved)!r} asked for, but this machine has {count} CUDA device(s)")
    elif resolved.type == "mps":
        raise DeviceUnavailableError("device 'mps' is not supported: the renderer's transmittance sums in float64, "
                                     "which MPS lacks; use device 'cpu' (or a CUDA device)")
    return resolved


def same_device(a: torch.device | str, b: torch.device | str) -> bool:
    """Whether two devices are one: an index-less ``cuda`` is the current CUDA device.

    Examples:
        >>> same_device("cpu", "cpu"), same_device("cuda:0", "cuda:1"), same_device("cuda:1", "cpu")
        (True, False, False)
    """
    a, b = torch.device(a), torch.device(b)
    if a.type != b.type:
        return False
    if a.index is None or b.index is None:  # asks CUDA which device is current only then
        current = torch.cuda.current_device() if a.type == "cuda" else 0
        return (current if a.index is None else a.index) == (current if b.index is None else b.index)
    return a.index == b.index


def _rss_peak_bytes() -> int | None:
    try:
        for line in _PROC_STATUS.read_text().splitlines():
            if line.startswith("VmHWM:"):
                return int(line.split()[1]) * 1024
    except OSError:
        pass
    try:
        import resource

        return int(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss) * 1024  # kB on Linux
    except (ImportError, OSError):
        return None


class PeakMemory:
    """High-water memory of one stage on ``device``: call :meth:`start` as the stage begins, read :meth:`info`.

    On CPU the figure is the whole process's resident peak since ``start`` (it
    includes the interpreter and loaded libraries: an upper bound on the stage);
    where the peak cannot be reset it is the process's lifetime peak. Each read
    keeps a running maximum, so a nested stage that resets the counter (the
    evaluation's ring renders) loses none of what was read before it.

    Examples:
        >>> memory = PeakMemory("cpu").start()
        >>> info = memory.info()
        >>> info["peak_memory_kind"], info["peak_memory_gb"] > 0
        ('process_rss', True)
    """

    def __init__(self, device: torch.device | str):
        self.device = torch.device(device)
        self._max_bytes: int | None = None

    @property
    def kind(self) -> str | None:
        if self.device.type == "cuda":
            return "cuda_allocated"
        return "process_rss" if self.device.type == "cpu" else None

    def start(self) -> "PeakMemory":
        if self.device.type == "cuda":
            torch.cuda.reset_peak_memory_stats(self.device)
        elif self.device.type == "cpu":
            try:
                _PROC_CLEAR_REFS.write_text("5")  # resets VmHWM to the current RSS (Linux >= 4.0)
            except OSError:
                pass
        return self

    def peak_bytes(self) -> int | None:
        if self.device.type == "cuda":
            current = int(torch.cuda.max_memory_allocated(self.device))
        else:
            current = _rss_peak_bytes() if self.device.type == "cpu" else None
        if current is not None:
            self._max_bytes = current if self._max_bytes is None else max(self._max_bytes, current)
        return self._max_bytes

    def info(self) -> dict[str, object]:
        """``{"peak_memory_gb": GiB or None, "peak_memory_kind": ...}``, for a Progress report's info; on CUDA also
        ``peak_memory_reserved_gb``, the caching allocator's peak, which counts what ``max_memory_allocated`` leaves
        out: CUDA graphs' private pools (a replay allocates nothing) and the allocator's cache."""
        peak = self.peak_bytes()
        info = {"peak_memory_gb": None if peak is None else round(peak / GIB, 4), "peak_memory_kind": self.kind}
        if self.device.type == "cuda":
            info["peak_memory_reserved_gb"] = round(torch.cuda.max_memory_reserved(self.device) / GIB, 4)
        return info


@contextmanager
def full_precision(*tensors: torch.Tensor):
    """Autocast disabled on every device type the tensors live on (nothing to disable where torch has none, e.g. meta):
    the renderer's transmittance products and the losses' correlations want float32."""
    with ExitStack() as stack:
        for device_type in sorted({t.device.type for t in tensors}):
            if torch.amp.is_autocast_available(device_type):
                stack.enter_context(torch.autocast(device_type=device_type, enabled=False))
        yield


def synchronize(device: torch.device | str) -> None:
    """Wait for the work queued on ``device`` (CUDA); nothing to wait for elsewhere. Timers call it around what
    they time, since CUDA returns before its kernels run."""
    device = torch.device(device)
    if device.type == "cuda":
        torch.cuda.synchronize(device)


__all__ = ["DeviceUnavailableError", "PeakMemory", "default_device", "full_precision", "resolve_device",
           "synchronize"]
