"""A rendered clip replayed slower than it was filmed: a phone's slow-motion file (times in seconds).

A phone writes its 120 or 240 fps slow motion to play at 30 fps, and Android says the filming rate in the file's
``com.android.capture.fps`` tag (:data:`fieldtool.processing.frames.CAPTURE_TAG`). :func:`replayed` makes such a
file from a rendered scene's clip, for the slow-motion tests and ``benchmarks/slow_motion.py``.
"""

from __future__ import annotations

from pathlib import Path

import av

from fieldtool.processing.frames import CAPTURE_TAG


def replayed(src: Path, dst: Path, slower: int, tag: str | None = None) -> None:
    """``src``'s frames, not re-encoded, in ``dst`` with every timestamp ``slower`` times later (the file plays
    ``slower`` times slower than it was filmed), and ``tag`` (the filming rate, frames per second, as text) as
    the phone's :data:`CAPTURE_TAG`; None: no tag."""
    with av.open(str(src)) as i, av.open(str(dst), "w", options={"movflags": "use_metadata_tags"}) as o:
        if tag is not None:
            o.metadata[CAPTURE_TAG] = tag
        ist = i.streams.video[0]
        ost = o.add_stream_from_template(ist)
        for pk in i.demux(ist):
            if pk.dts is None or pk.pts is None:  # the demuxer's flush packet
                continue
            pk.pts, pk.dts, pk.stream = pk.pts * slower, pk.dts * slower, ost
            o.mux(pk)
