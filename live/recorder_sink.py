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
        device: the device's topic name when the file holds several devices: its events
            then carry it (``device`` field, and the message starts with it).
    """

    def __init__(self, recorder: Any, acquisition: Any, device: str | None = None) -> None:
        self.recorder = recorder
        self.acquisition = acquisition
        self.device = device
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
        if self.device is not None:
            message = f"{self.device}: {message}"
            fields = {**fields, "device": self.device}
        self.recorder.event(lv, message, fields, t=t)

    def _event(self, state: str, t: float | None) -> None:
        self.note("ok" if state in ("running", "ok") else "warn", f"device state: {state}",
                  {"event": "state", "state": state}, t)

    def close(self) -> None:
        self.recorder.close()


class GroupRecorderSink:
    """The recorder of several devices (:class:`imunoise.daq.device_group.DeviceGroup`) in one
    file: each block goes through its device's :class:`RecorderSink` (found by the block's
    topic name), so that every device's state changes become events of their own.

    Args:
        recorder: as for :class:`RecorderSink`.
        group: the device group (its ``members``: ``(topic name, acquisition)``).
    """

    def __init__(self, recorder: Any, group: Any) -> None:
        from imunoise.daq.device_group import device_of_stream

        self._device_of = device_of_stream
        self.recorder = recorder
        self.sinks = {name: RecorderSink(recorder, acq, device=name)
                      for name, acq in group.members}

    def write(self, block: Any, payload: bytes | None = None) -> None:
        sink = self.sinks.get(self._device_of(str(block.stream)))
        if sink is None:  # not a device of the group: recorded, no state watched
            if payload is None:
                self.recorder.write(block)
            else:
                self.recorder.write(block, payload=payload)
            return
        sink.write(block, payload)

    def note(self, level: str, message: str, fields: dict[str, str],
             t: float | None = None) -> None:
        """A status event of the whole group."""
        RecorderSink(self.recorder, None).note(level, message, fields, t)

    def close(self) -> None:
        self.recorder.close()
