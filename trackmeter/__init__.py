"""TV-Trackmeter: stereo tracking and motion estimation of a tumbling satellite.

Layers, bottom to top (imports only go upward):

1. ``trackmeter.core``     pure maths, no I/O, no threads
2. ``trackmeter.data``     files: configs, rigs, sequences, trajectories, models
3. ``trackmeter.sources``  where stereo frames come from (simulator, sequences, cameras)
4. ``trackmeter.pipeline`` threads, commands, snapshots, recording
5. ``trackmeter.cli``      the ``trackmeter`` command

Conventions (frames, units, names) are in ``docs/conventions.md``.
"""

from trackmeter.errors import TrackmeterError

__version__ = "0.1.0"
__all__ = ["TrackmeterError", "__version__"]
