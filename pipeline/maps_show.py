"""Two names ``stages/tiles/cli.py`` imports from here (its ``tiles ls``), kept only until that file imports them
from the store: ``pipeline.version_read.version_states`` and ``state_note``. ``cornermap maps show`` is
``mapservice/maps_show.py`` (issue 61). Delete this module when ``stages/tiles/cli.py`` no longer names it."""

from pipeline.version_read import state_note, version_states  # noqa: F401
