"""Ingest parameters (defaults in code; unknown keys rejected)."""
from __future__ import annotations

from pydantic import Field

from pipeline.declare import Params


class IngestParams(Params):
    chunk_size_scans: int = Field(100, ge=1, description="scans per chunk (the partition of downstream stages)")
    max_scans: int | None = Field(None, ge=1, description="ingest only the first N scans (smoke runs)")
    gnss_gap_s: float = Field(1.0, gt=0, description="GNSS fixes further apart than this are a gap (flagged; "
                                                      "poses inside are valid=false)")
    min_range_m: float = Field(0.0, ge=0, description="drop points closer than this to the sensor (0 = keep)")
    survey_chunk_points: int = Field(1_000_000, ge=1000, description="survey points per streamed table")
    ring_vote_min_share: float = Field(0.5, gt=0, le=1, description="majority a firing slot needs before "
                                                                     "elevation-table rings are voted per slot")
    gnss_default_std_east_m: float = Field(1.0, gt=0, description="GNSS std east used when the file has no std "
                                                                  "column (a warning names it)")
    gnss_default_std_north_m: float = Field(1.0, gt=0, description="GNSS std north when the file has none")
    gnss_default_std_up_m: float = Field(2.0, gt=0, description="GNSS std up when the file has none")
    gnss_default_std_heading_deg: float = Field(1.0, gt=0, description="heading std when the file has none")
    gnss_max_speed_mps: float = Field(100.0, gt=0, description="a fix further from the previous one than this "
                                                                "speed allows is rejected (per row, with a reason)")
    gnss_height_min_m: float = Field(-1000.0, description="fixes below this ellipsoidal height are rejected")
    gnss_height_max_m: float = Field(10000.0, description="fixes above this ellipsoidal height are rejected")
    prior_gap_s: float = Field(1.0, gt=0, description="a scan stamp between two prior-trajectory rows further apart "
                               "than this has no prior pose (valid=false), unless a row lies at its stamp")
    prior_as_gnss: bool = Field(False, description="a drive without GNSS takes its prior trajectory (ENU, or local "
                                "aligned at the start heading) as its poses_gnss (the prior's std; a local prior's "
                                "grown by the start's heading std per metre), treated as GNSS fixes by the pose "
                                "graph; off (default): poses_gnss rows without a fix (valid false), the pose graph "
                                "reads poses_prior as pose priors with the stated std")
