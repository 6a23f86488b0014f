"""Two names ``stages/tiles/cli.py`` imports from here (its ``tiles rollback``), kept only until that file imports
them from the store: ``pipeline.versioned.rollback_latest``. The map service is ``mapservice/`` (issue 61).
Delete this module when ``stages/tiles/cli.py`` no longer names it."""

from pipeline.versioned import rollback_latest as rollback  # noqa: F401
