"""Recording every cycle to an MCAP file, and reading it back.

    rec = op.record("run.mcap")            # or: fieldbus run/demo/soak --record run.mcap
    ...                                    # every exchange() is recorded
    rec.close()                            # or op.close()
    r = fieldbus.recording.load("run.mcap")
    r.groups["joints"]["inputs"]["position_actual_value"]    # (cycles, axes) numpy array

Modules: :mod:`~fieldbus.recording.ring` (the cycle's preallocated ring),
:mod:`~fieldbus.recording.writer` (the writer thread, MCAP),
:mod:`~fieldbus.recording.events`, :mod:`~fieldbus.recording.schema`,
:mod:`~fieldbus.recording.load`. The format is described in docs/observability.md.
"""

from fieldbus.recording.load import Recording, load
from fieldbus.recording.writer import Recorder, RecordingWarning, check_writable

__all__ = ["Recorder", "Recording", "RecordingWarning", "check_writable", "load"]
