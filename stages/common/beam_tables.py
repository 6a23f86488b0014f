"""Published beam elevation tables of the sensors users bring (degrees, as published: top beam first).

Ouster publishes no nominal table: every unit carries its own calibration in its metadata JSON
(``beam_altitude_angles``). The tables here are real units' metadata as Ouster publishes them with its SDK's test
data (ouster-lidar/ouster-sdk, ``tests/``), each named by the file and its ``prod_line``. Ouster builds its 32 and 64
channel configurations from the 128-laser array of the same family (product codes: ``U`` uniform = every 2nd
(``U02``) or 4th (``U0``) laser counted from the lowest; ``BH`` below horizon = the lower half; ``G`` gradient);
configurations without a published example are derived from the family's 128-channel example that way, and the
rule is checked on one unit whose 32-U0 and 64-U02 metadata are both published (OS0 882002000138:
``tests/stages/ingest/test_sensor_tables.py``). A unit differs from another by a few 0.1 degree: give the sensor's
own metadata (``calibration_file``) where it exists.

Velodyne VLP-32C: the nominal table of Velodyne's VeloView calibration ``VLP-32c.xml`` (id order). Hesai Pandar64:
the angle-correction file Hesai publishes with its SDK (HesaiLidar_SDK_2.0 ``Pandar64E3X_Angle Correction File``);
PandarXT32: Hesai's nominal table (HesaiLidar_General_SDK ``pandarXT.h``: +15 .. -16 deg in 1 deg steps).
"""
from __future__ import annotations

# Ouster OS1-128 (rev 7), ouster-sdk tests/metadata/3_0_1_os-122246000293.json, prod_line OS-1-128.
OS1_128 = (
    20.47, 20.21, 19.89, 19.54, 19.23, 18.97, 18.66, 18.31, 18.0, 17.72, 17.4, 17.05, 16.74, 16.45, 16.13, 15.77,
    15.45, 15.15, 14.83, 14.47, 14.15, 13.85, 13.52, 13.17, 12.83, 12.52, 12.19, 11.83, 11.5, 11.18, 10.85, 10.5,
    10.14, 9.82, 9.49, 9.14, 8.79, 8.45, 8.13, 7.76, 7.42, 7.08, 6.75, 6.39, 6.04, 5.7, 5.35, 5.0, 4.64, 4.32, 3.98,
    3.61, 3.25, 2.92, 2.57, 2.22, 1.85, 1.52, 1.17, 0.82, 0.45, 0.12, -0.24, -0.58, -0.95, -1.28, -1.64, -1.97, -2.35,
    -2.69, -3.03, -3.37, -3.74, -4.1, -4.43, -4.77, -5.14, -5.49, -5.82, -6.17, -6.53, -6.88, -7.22, -7.55, -7.91,
    -8.27, -8.6, -8.92, -9.28, -9.64, -9.97, -10.29, -10.65, -11.01, -11.33, -11.64, -12.01, -12.35, -12.69, -12.98,
    -13.34, -13.69, -14.03, -14.32, -14.68, -15.02, -15.35, -15.63, -15.98, -16.34, -16.65, -16.93, -17.27, -17.63,
    -17.93, -18.21, -18.55, -18.9, -19.2, -19.48, -19.81, -20.16, -20.46, -20.72, -21.05, -21.39, -21.68, -21.95,
)

# Ouster OS2-128, ouster-sdk tests/pcaps/OS-2-128-U1_v2.3.0_1024x10.json, prod_line OS-2-128.
OS2_128 = (
    10.76, 10.58, 10.42, 10.24, 10.1, 9.93, 9.76, 9.57, 9.41, 9.24, 9.09, 8.91, 8.75, 8.57, 8.41, 8.23, 8.08, 7.9,
    7.74, 7.55, 7.39, 7.21, 7.03, 6.86, 6.7, 6.53, 6.35, 6.18, 6.02, 5.83, 5.67, 5.5, 5.32, 5.14, 4.97, 4.81, 4.63,
    4.46, 4.28, 4.11, 3.95, 3.76, 3.58, 3.43, 3.24, 3.07, 2.9, 2.72, 2.55, 2.37, 2.21, 2.03, 1.87, 1.69, 1.51, 1.32,
    1.16, 0.98, 0.81, 0.63, 0.46, 0.29, 0.11, -0.05, -0.25, -0.42, -0.58, -0.76, -0.93, -1.11, -1.28, -1.45, -1.63,
    -1.81, -1.97, -2.16, -2.32, -2.5, -2.68, -2.85, -3.02, -3.19, -3.37, -3.55, -3.73, -3.9, -4.07, -4.25, -4.4,
    -4.58, -4.75, -4.94, -5.11, -5.28, -5.46, -5.64, -5.8, -5.96, -6.15, -6.32, -6.49, -6.66, -6.84, -7.0, -7.17,
    -7.35, -7.51, -7.69, -7.86, -8.04, -8.22, -8.38, -8.55, -8.72, -8.89, -9.06, -9.23, -9.4, -9.57, -9.74, -9.91,
    -10.07, -10.24, -10.41, -10.58, -10.75, -10.92, -11.09,
)

# Ouster OS1-64 (first generation, 33.2 deg), ouster-sdk tests/metadata/2_0_0_os1-991913000010-64.json, prod_line
# OS-1-64.
OS1_64_GEN1 = (
    16.729, 16.118, 15.543, 14.995, 14.526, 13.937, 13.381, 12.837, 12.378, 11.801, 11.251, 10.704, 10.251, 9.693,
    9.138, 8.603, 8.149, 7.594, 7.049, 6.513, 6.056, 5.504, 4.961, 4.419, 3.967, 3.424, 2.881, 2.328, 1.88, 1.337,
    0.787, 0.239, -0.205, -0.756, -1.39, -1.854, -2.3, -2.839, -3.386, -3.935, -4.391, -4.929, -5.472, -6.028,
    -6.471, -7.02, -7.563, -8.116, -8.572, -9.112, -9.66, -10.227, -10.687, -11.226, -11.777, -12.35, -12.807,
    -13.347, -13.902, -14.49, -14.968, -15.504, -16.078, -16.679,
)

# Ouster OS1-32 gradient, ouster-sdk tests/pcaps/OS-1-32-G_v2.1.1_1024x10.json, prod_line OS-1-32-G.
OS1_32_G = (
    12.75, 10.03, 7.27, 4.47, 3.41, 2.35, 2.02, 1.65, 1.29, 0.93, 0.6, 0.23, -0.13, -0.49, -0.83, -1.17, -1.54,
    -1.88, -2.24, -2.6, -2.96, -3.65, -4.36, -5.06, -5.76, -7.17, -8.57, -9.95, -11.31, -12.66, -14.01, -15.32,
)

# Ouster OS2-32 uniform, ouster-sdk tests/pcaps/OS-2-32-U0_v2.0.0_1024x10.json, prod_line OS-2-32-U0.
OS2_32_U0 = (
    10.87, 10.24, 9.56, 8.88, 8.2, 7.52, 6.83, 6.14, 5.44, 4.76, 4.06, 3.35, 2.66, 1.96, 1.27, 0.56, -0.12, -0.83,
    -1.51, -2.22, -2.92, -3.61, -4.32, -5.02, -5.7, -6.4, -7.08, -7.77, -8.47, -9.14, -9.82, -10.48,
)

# One OS0 unit (882002000138) in two configurations, ouster-sdk tests/assets/1_14_6cccd_os-882002000138-64U02.json
# (prod_line OS-0-64-U02) and ...-32U0.json (OS-0-32-U0): the check of the configuration rule above (no OS0 model).
OS0_64_U02_CHECK = (
    45.12, 43.9, 42.09, 40.87, 39.09, 37.86, 36.11, 34.88, 33.16, 31.92, 30.24, 28.99, 27.33, 26.07, 24.44, 23.17,
    21.57, 20.29, 18.72, 17.42, 15.87, 14.56, 13.04, 11.71, 10.21, 8.862, 7.388, 6.023, 4.572, 3.188, 1.758, 0.3541,
    -1.055, -2.479, -3.868, -5.314, -6.684, -8.152, -9.503, -10.99, -12.33, -13.84, -15.16, -16.7, -18.0, -19.57,
    -20.86, -22.45, -23.72, -25.34, -26.61, -28.26, -29.51, -31.19, -32.43, -34.14, -35.37, -37.11, -38.34, -40.11,
    -41.33, -43.14, -44.36, -46.2,
)
OS0_32_U0_CHECK = (
    43.9, 40.87, 37.86, 34.88, 31.92, 28.99, 26.07, 23.17, 20.29, 17.42, 14.56, 11.71, 8.862, 6.023, 3.188, 0.3541,
    -2.479, -5.314, -8.152, -10.99, -13.84, -16.7, -19.57, -22.45, -25.34, -28.26, -31.19, -34.14, -37.11, -40.11,
    -43.14, -46.2,
)

# Velodyne VLP-32C, VeloView VLP-32c.xml vertCorrection_ by laser id 0..31.
VLP32C = (
    -25.0, -1.0, -1.667, -15.639, -11.31, 0.0, -0.667, -8.843, -7.254, 0.333, -0.333, -6.148, -5.333, 1.333, 0.667,
    -4.0, -4.667, 1.667, 1.0, -3.667, -3.333, 3.333, 2.333, -2.667, -3.0, 7.0, 4.667, -2.333, -2.0, 15.0, 10.333,
    -1.333,
)

# Hesai Pandar64, HesaiLidar_SDK_2.0 correction/angle_correction/Pandar64E3X_Angle Correction File.csv (channel 1..64).
PANDAR64 = (
    14.837607, 10.982645, 8.003339, 5.016721, 3.022091, 1.999304, 1.813281, 1.673738, 1.509076, 1.318152, 1.139504,
    0.981214, 0.800679, 0.663732, 0.505692, 0.306812, 0.168143, -0.023681, -0.178967, -0.348336, -0.531367,
    -0.722312, -0.869764, -1.043586, -1.217363, -1.354845, -1.550417, -1.715686, -1.874733, -2.058432, -2.240654,
    -2.375897, -2.545819, -2.732423, -2.872055, -3.087116, -3.230261, -3.388678, -3.542589, -3.756515, -3.891862,
    -4.093821, -4.241211, -4.424695, -4.574435, -4.749833, -4.900231, -5.09038, -5.247624, -5.425348, -5.595772,
    -5.779886, -5.877936, -6.10903, -7.097081, -8.090181, -9.080228, -10.084443, -11.051773, -12.01823, -13.022724,
    -13.951096, -18.912931, -24.883393,
)

# Hesai PandarXT32, HesaiLidar_General_SDK pandarXT.h pandarXT_elev_angle_map.
PANDARXT32 = tuple(float(v) for v in range(15, -17, -1))


def lasers_from_lowest(table: tuple[float, ...], step: int, start: int = 0, lower_half: bool = False
                       ) -> tuple[float, ...]:
    """An Ouster channel configuration from its family's 128-laser table: every ``step``-th laser counted from the
    lowest (starting at ``start``), of the lower half only with ``lower_half`` (below horizon); ascending."""
    ascending = sorted(table)
    lasers = ascending[: len(ascending) // 2] if lower_half else ascending
    return tuple(lasers[start::step])
