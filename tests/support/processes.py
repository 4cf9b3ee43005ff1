"""A process's children and whether they still run (Linux /proc), for tests that stop ringscan's pools."""

from __future__ import annotations

from pathlib import Path


def children(pid: int) -> list[int]:
    """The process ids of ``pid``'s children (empty when it is gone)."""
    try:
        return [int(c) for c in Path(f"/proc/{pid}/task/{pid}/children").read_text().split()]
    except OSError:
        return []


def running(pid: int) -> bool:
    """Whether process ``pid`` runs (neither gone nor a zombie)."""
    try:
        return "State:\tZ" not in Path(f"/proc/{pid}/status").read_text()
    except OSError:
        return False


def as_foreground_job() -> None:
    """``preexec_fn`` for a child that is to receive a terminal's Ctrl-C: SIGINT at its default. A shell
    starts background jobs (``make test &``, a CI runner's script) with SIGINT ignored, every descendant
    inherits that, and Python keeps it ignored: the child would never see the test's SIGINT."""
    import signal

    signal.signal(signal.SIGINT, signal.SIG_DFL)
