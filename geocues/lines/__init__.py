"""Line cues (paper §4.1): 2D segments -> matched -> triangulated, scored, merged 3D segments.

Entry point (the stage chain in ``geocues.extract`` calls it)::

    from geocues.lines import LineConfig, LineCues, extract_line_cues
    cues = extract_line_cues(scene, LineConfig(), cache_dir)   # cache_dir: Path | None
"""

from geocues.lines.config import LineConfig, LineCues
from geocues.lines.pipeline import extract_line_cues

__all__ = ["LineConfig", "LineCues", "extract_line_cues"]
