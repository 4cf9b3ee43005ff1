"""A call run in a thread with a time limit, for the tests that a read or a command does not block (a FIFO,
a device file) and would hang the test process if it did."""

from __future__ import annotations

import threading


def in_thread(fn, timeout=10.0):
    """Run fn in a thread; its result or exception, or 'hung' when it does not return in time."""
    box = {}

    def target():
        try:
            box["value"] = fn()
        except BaseException as e:  # noqa: BLE001 - handed to the test
            box["error"] = e

    t = threading.Thread(target=target, daemon=True)
    t.start()
    t.join(timeout)
    if t.is_alive():
        return "hung"
    return box.get("error", box.get("value"))
