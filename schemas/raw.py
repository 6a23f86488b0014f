"""Schemas written by ingest: raw scans in the sensor frame, GNSS/INS in ENU, odometry, survey cloud."""
import pyarrow as pa

from schemas.registry import field as f
from schemas.registry import register

DRIVE = f("drive", pa.string(), doc="drive name from the workflow")
CHUNK = f("chunk", pa.int32(), doc="scan chunk index within the drive")

register(
    "scans_raw", "LiDAR points per scan in the sensor (lidar) frame; x forward, y left, z up.",
    DRIVE, CHUNK,
    f("scan_id", pa.int64(), doc="0-based scan index within the drive"),
    f("stamp_ns", pa.int64(), "ns", doc="scan start time, drive time base"),
    f("x_m", pa.float32(), "m", "lidar"), f("y_m", pa.float32(), "m", "lidar"), f("z_m", pa.float32(), "m", "lidar"),
    f("intensity", pa.float32(), "raw", doc="uncalibrated return intensity as recorded"),
    f("ring", pa.int16(), doc="laser index, 0 = lowest beam"),
    f("time_offset_s", pa.float32(), "s", doc="point time minus scan stamp"),
    row_group_key="scan_id",
)

register(
    "scan_index", "One row per scan file: counts, drops and quarantine status.",
    DRIVE, CHUNK,
    f("scan_id", pa.int64()), f("stamp_ns", pa.int64(), "ns"),
    f("source_file", pa.string(), doc="path relative to the drive folder"),
    f("n_points", pa.int64()), f("n_dropped_nonfinite", pa.int64()), f("n_dropped_zero", pa.int64()),
    f("rings_present", pa.int32(), doc="number of distinct rings with points"),
    f("ring_source", pa.string(), doc="file | elevation_table | point_order"),
    f("status", pa.string(), doc="ok | quarantined"),
    f("reason", pa.string(), nullable=True),
)

register(
    "gnss_enu", "GNSS/INS solution in the map's ENU frame, vehicle reference point.",
    DRIVE,
    f("stamp_ns", pa.int64(), "ns"),
    f("east_m", pa.float64(), "m", "enu"), f("north_m", pa.float64(), "m", "enu"), f("up_m", pa.float64(), "m", "enu"),
    f("roll_rad", pa.float64(), "rad", doc="NaN when the file has no roll/pitch"),
    f("pitch_rad", pa.float64(), "rad", doc="NaN when the file has no roll/pitch"),
    f("yaw_enu_rad", pa.float64(), "rad", "enu", doc="counter-clockwise from east"),
    f("std_east_m", pa.float64(), "m"), f("std_north_m", pa.float64(), "m"), f("std_up_m", pa.float64(), "m"),
    f("std_yaw_rad", pa.float64(), "rad"),
)

register(
    "odometry_raw", "Wheel speed and gyro yaw rate.",
    DRIVE,
    f("stamp_ns", pa.int64(), "ns"),
    f("speed_mps", pa.float64(), "m/s"), f("yaw_rate_radps", pa.float64(), "rad/s"),
)

register(
    "poses_gnss", "GNSS/INS pose of the vehicle interpolated to each scan stamp (T_map_vehicle).",
    DRIVE,
    f("scan_id", pa.int64()), f("stamp_ns", pa.int64(), "ns"),
    f("x_m", pa.float64(), "m", "enu"), f("y_m", pa.float64(), "m", "enu"), f("z_m", pa.float64(), "m", "enu"),
    f("qx", pa.float64()), f("qy", pa.float64()), f("qz", pa.float64()), f("qw", pa.float64()),
    f("std_east_m", pa.float64(), "m"), f("std_north_m", pa.float64(), "m"), f("std_up_m", pa.float64(), "m"),
    f("std_yaw_rad", pa.float64(), "rad"),
    f("valid", pa.bool_(), doc="false inside a GNSS outage (no fix within the gap threshold)"),
    f("roll_pitch_known", pa.bool_(), doc="false: the GNSS/INS gives no roll/pitch (the attitude holds yaw only "
                                          "and must not be used as a roll/pitch prior)"),
)

register(
    "poses_prior", "A trajectory the drive file names (prior:) at each scan stamp, and the drive's stated start pose "
    "(start:); T_frame_vehicle, std per axis (NaN: nothing known on that axis).",
    DRIVE,
    f("scan_id", pa.int64()), f("stamp_ns", pa.int64(), "ns"),
    f("x_m", pa.float64(), "m", "frame"), f("y_m", pa.float64(), "m", "frame"), f("z_m", pa.float64(), "m", "frame"),
    f("qx", pa.float64()), f("qy", pa.float64()), f("qz", pa.float64()), f("qw", pa.float64()),
    f("std_x_m", pa.float64(), "m"), f("std_y_m", pa.float64(), "m"), f("std_z_m", pa.float64(), "m"),
    f("std_roll_rad", pa.float64(), "rad"), f("std_pitch_rad", pa.float64(), "rad"),
    f("std_yaw_rad", pa.float64(), "rad"),
    f("frame", pa.string(), doc="map_enu: the map's ENU frame; local: the prior file's own frame (z up, origin and "
                                "heading unknown: only its relative motion is information)"),
    f("source", pa.string(), doc="prior_file | start"),
    f("valid", pa.bool_(), doc="the scan stamp lies within the prior's span (interpolated between two rows)"),
)

register(
    "drive_info", "Per drive: sensor, extrinsic T_vehicle_lidar (row-major 4x4), ENU origin, counts.",
    DRIVE,
    f("sensor", pa.string()),
    f("T_vehicle_lidar", pa.list_(pa.float64(), 16), doc="row-major 4x4, maps lidar points into the vehicle frame"),
    f("origin_lat_deg", pa.float64(), "deg"), f("origin_lon_deg", pa.float64(), "deg"),
    f("origin_h_m", pa.float64(), "m", doc="WGS84 ellipsoidal height"),
    f("n_scans", pa.int64()), f("n_quarantined", pa.int64()),
    f("drive_file", pa.string()),
)

register(
    "survey_enu", "Survey (mobile-mapping) point cloud in the map's ENU frame.",
    DRIVE,
    f("east_m", pa.float64(), "m", "enu"), f("north_m", pa.float64(), "m", "enu"), f("up_m", pa.float64(), "m", "enu"),
    f("intensity", pa.float32(), "raw"),
)

register(
    "ingest_report", "Everything ingest dropped, quarantined or flagged, by file and record.",
    DRIVE,
    f("kind", pa.string(), doc="quarantined_file | dropped_points | timestamp | gnss_gap | ring_coverage"),
    f("file", pa.string()), f("record", pa.int64(), nullable=True),
    f("count", pa.int64()), f("reason", pa.string()),
)
