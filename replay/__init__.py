"""``socd replay``: recorded drive cycles and CAN logs played onto a CAN bus.

Library API (used by the demo and the tests)::

    from replay.pack import pack_frames, SpreadSpec, PackRecording
    from replay.player import play, read_log, ReplayStats
    from replay.faults import FaultSpec, FaultInjector
"""
