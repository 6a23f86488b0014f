"""The map service above the engine and the stages: a map as a maintained thing and the top-level ``cornermap`` app.

- ``cli``: the root app and its exit codes; it assembles the engine's commands (``pipeline.engine_cli``), the
  stages' and the service's own (``maps_cli``: ``maps create|show|reoptimize``, ``rebuild``, ``gc``; ``build``).
- ``maps``: a map's identity (pinned ENU origin, tile size, area, drive set), ``MapHome`` (local root or bucket).
- ``build``: the standard map workflow on given drives; ``rebuild`` (an inbox of new drives, the regression
  ``gate``, publish), ``reoptimize``; ``inbox`` (deliveries, quarantine); ``gc``; ``maps_show``; ``child``.

It may import the engine (``pipeline``), the stages, the map format and the schemas; none of them imports it
(the import contracts in pyproject.toml).
"""
