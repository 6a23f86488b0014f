"""The map's ENU origin: the workflow's, else the first GNSS fix of the first drive (in workflow order) that
has GNSS, else the origin of the first drive's prior trajectory in ENU (``prior.origin``), else the first drive's
stated start position. Every per-drive task computes the same answer from the same files, so parallel tasks agree."""
from __future__ import annotations

import logging
from pathlib import Path
from typing import Iterable, Mapping

from pipeline.errors import ConfigError
from stages.common.geodesy import EnuOrigin, OriginError
from stages.ingest.drive_file import load_drive_file
from stages.ingest.gnss_csv import read_first_fix

log = logging.getLogger(__name__)


def resolve_enu_origin(settings_origin: Mapping | None, drive_paths_in_order: Iterable[str | Path]
                       ) -> EnuOrigin | None:
    if settings_origin:
        try:
            return EnuOrigin.validate(dict(settings_origin))
        except OriginError as exc:
            raise ConfigError("workflow enu_origin", exc.problems) from None
    specs = [(path, load_drive_file(path)) for path in drive_paths_in_order]
    for path, spec in specs:
        if spec.gnss is None:
            continue
        fix = read_first_fix(spec.path(spec.gnss.file), spec.gnss)
        if fix is not None:
            log.info("ENU origin from the first GNSS fix of %s: %s", path, fix)
            return EnuOrigin(*fix)
    for path, spec in specs:
        stated = spec.prior.origin if spec.prior is not None and spec.prior.frame == "enu" else \
            (spec.start.position if spec.start is not None else None)
        if stated is not None:
            log.info("ENU origin from %s of %s: %s", "the prior's" if spec.prior else "the start position", path,
                     stated)
            return EnuOrigin(stated.lat_deg, stated.lon_deg, stated.h_m)
    return None
