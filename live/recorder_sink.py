"""The recorder as a sink of live blocks: every block to the MCAP file, and the device's state
changes (reconnecting, running, failed) as status events in the same file."""

from __future__ import annotations

from typing import Any


class RecorderSink:
    """Feeds a recorder and records device state changes.

    Args:
        recorder: the open recorder: a :class:`imunoise.daq.recorder.McapRecorder`, or in the
            acquisition process a :class:`imunoise.live.recorder_process.RecorderProcess`.
        acquisition: the source whose ``stats`` (``state``, ``reconnects``, ``last_error``)
            are watched; any object (its missing attributes read as empty).
    """

    def __init__(self, recorder: Any, acquisition: Any) -> None:
        self.recorder = recorder
        self.acquisition = acquisition
        self._state: str | None = None
        self._reconnects = 0

    def write(self, block: Any, payload: bytes | None = None) -> None:
        """Record a block; ``payload``: the block already pickled, for a recorder in another
        process (:class:`imunoise.live.recorder_process.RecorderProcess`), which then sends it as
        is."""
        if payload is None:
            self.recorder.write(block)
        else:
            self.recorder.write(block, payload=payload)  # McapRecorder's 2nd is wall
        stats = getattr(self.acquisition, "stats", None)
        state = str(getattr(stats, "state", ""))
        reconnects = int(getattr(stats, "reconnects", 0) or 0)
        t = float(block.t[-1]) if len(block) else None
        # States are sampled when a block arrives; an outage that ended between two blocks
        # shows only in the reconnect count, and is recorded as the change it was.
        if (self._state is not None and reconnects > self._reconnects
                and state == self._state == "running"):
            reason = str(getattr(stats, "last_error", "") or "")
            self._event("reconnecting" + (f" ({reason})" if reason else ""), t)
            self._state = "reconnecting"
        if self._state is not None and state != self._state:
            self._event(state, t)
        self._state = state
        self._reconnects = reconnects

    def note(self, level: str, message: str, fields: dict[str, str],
             t: float | None = None) -> None:
        """A status event in the file (``level``: ``"ok"``, ``"warn"`` or ``"error"``)."""
        from imunoise.daq import ros2_msgs

        lv = {"ok": ros2_msgs.OK, "warn": ros2_msgs.WARN}.get(level, ros2_msgs.WARN)
        self.recorder.event(lv, message, fields, t=t)

    def _event(self, state: str, t: float | None) -> None:
        self.note("ok" if state in ("running", "ok") else "warn", f"device state: {state}",
                  {"event": "state", "state": state}, t)

    def close(self) -> None:
        self.recorder.close()
