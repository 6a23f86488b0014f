"""The map's ENU origin: the workflow's, else the first GNSS fix of the first drive (in workflow order) that
has GNSS. Every per-drive task computes the same answer from the same files, so parallel tasks agree."""
from __future__ import annotations

import logging
from pathlib import Path
from typing import Iterable, Mapping

from stages.common.geodesy import EnuOrigin
from stages.ingest.drive_file import load_drive_file
from stages.ingest.gnss_csv import read_first_fix

log = logging.getLogger(__name__)


def resolve_enu_origin(settings_origin: Mapping | None, drive_paths_in_order: Iterable[str | Path]
                       ) -> EnuOrigin | None:
    if settings_origin:
        return EnuOrigin.from_dict(dict(settings_origin))
    for path in drive_paths_in_order:
        spec = load_drive_file(path)
        if spec.gnss is None:
            continue
        fix = read_first_fix(spec.path(spec.gnss.file), spec.gnss)
        if fix is not None:
            log.info("ENU origin from the first GNSS fix of %s: %s", path, fix)
            return EnuOrigin(*fix)
    return None
