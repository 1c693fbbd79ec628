"""Sensor models for the PX4 simulator link: IMU, magnetometer, barometer, GPS.

Every sensor reads the twin's **true** state and adds, per axis, a constant bias
and zero-mean white Gaussian noise — the model of the Quad-C verification
reference (``/work/shared/reference/quad-c-model-verification.md``: "true value +
bias + zero-mean white Gaussian noise, per axis") — except the GPS position, whose
error is correlated in time as a real receiver's is: a first-order Gauss-Markov
process (σ ``gps_noise_m``, correlation time ``gps_correlation_time_s``) plus a small
white noise (``gps_white_noise_m``).  White GPS noise of 0.5 m at 10 Hz trips PX4's
pre-flight drift check (EKF2: the position's finite-difference rate, low-passed with a
10 s time constant, must stay below ``EKF2_REQ_HDRIFT`` 0.1 m/s), which real PX4 SITL
reported 8-25 times a flight (issue 14).  Noise comes from a ``np.random.Generator``
seeded from the config, so a run is reproducible.

Output frames are PX4's: body **FRD** for accel/gyro/mag, **NED** for GPS
velocity; the twin's ENU/FLU state is converted with :mod:`twin_nodes.base.frames`
only.

The ``sensors:`` block of a vehicle parameter file (all keys optional)::

    sensors:
      gyro_noise_rad_s:  [8.7e-4, 8.7e-4, 8.7e-4]   # white noise σ per sample, FRD axes
      gyro_bias_rad_s:   [1.0e-3, -7.0e-4, 5.0e-4]  # constant bias, FRD axes
      accel_noise_m_s2:  [0.044, 0.044, 0.044]      # white noise σ per sample, FRD axes
      accel_bias_m_s2:   [0.04, -0.03, 0.05]        # constant bias, FRD axes
      mag_noise_gauss:   0.002                      # σ per axis
      baro_noise_hpa:    0.012                      # σ of abs_pressure
      gps_noise_m:       0.5                        # σ per axis (N, E, D) of the correlated position error
      gps_correlation_time_s: 90.0                  # its correlation time (0 = white noise, the old model)
      gps_white_noise_m: 0.03                       # σ per axis of the white noise on top
      gps_vel_noise_m_s: 0.05                       # σ per axis of the NED velocity
      gps_rate_hz:  10.0
      mag_rate_hz:  100.0
      baro_rate_hz: 50.0
      home_lat_deg: 47.397743                       # where ENU (0, 0, 0) is
      home_lon_deg: 8.545594
      home_alt_m:   489.4                           # AMSL of the ground (z_enu = 0)
      seed: 0

Defaults (an MPU-6000 / HMC5883L / MS5611 / u-blox class vehicle):

- gyro σ 0.05 °/s = 8.7e-4 rad/s (MPU-6000 rate noise, reference table);
  bias ≈ 0.03–0.06 °/s, a typical residual after PX4's gyro calibration.
- accel σ = 400 µg/√Hz × √(125 Hz) = 0.044 m/s² (MPU-6000 density over the
  Nyquist band of the 250 Hz link); bias ≈ 3–5 mg, a post-calibration residual.
- mag σ 2 mG (HMC5883L resolution); baro σ 0.012 hPa ≈ 10 cm (MS5611
  resolution); GPS position error σ 0.5 m per axis, correlated over 90 s (a u-blox
  M8 at rest wanders by decimetres over tens of seconds; its 2.5 m CEP is absolute
  accuracy), plus 3 cm white noise, and velocity σ 0.05 m/s white.  With these the
  10 s low-passed position rate at rest stays below 0.075 m/s (20 seeds × 600 s
  simulated; PX4's limit 0.1 m/s) while white 0.5 m noise exceeds it.

A noise σ of 0 is allowed, but PX4 flags a sensor whose value never changes as
stale (a noiseless baro on a vehicle at rest blocks arming), so keep the baro
and mag noise above zero when flying with real PX4.

The Earth field is PX4's own WMM-2020 table (``geo_magnetic_tables.hpp``, epoch
2023.6) interpolated bilinearly, as ``get_mag_*`` does, at the SIH origin
(47.397743°, 8.545594°): declination 3.274°, inclination 63.144°, 0.48197 G.
It is not recomputed when ``home_*`` moves; a field far from the truth fails
PX4's ``EKF2_MAG_CHECK`` strength/inclination gates.
"""

from __future__ import annotations

from dataclasses import dataclass, fields
from typing import Any, Mapping

import numpy as np

from twin_nodes.base import frames
from twin_nodes.base.constants import G_STANDARD_M_S2
from twin_nodes.base.errors import ParamsError

__all__ = [
    "SIH_ORIGIN_LAT_DEG", "SIH_ORIGIN_LON_DEG", "SIH_ORIGIN_ALT_M",
    "MAG_DECLINATION_RAD", "MAG_INCLINATION_RAD", "MAG_STRENGTH_GAUSS",
    "SensorConfig", "SensorModel", "GpsFix",
    "mag_field_ned_gauss", "isa_pressure_pa", "isa_altitude_m", "isa_temperature_c",
    "reproject_ne_to_latlon", "project_latlon_to_ne",
]

SIH_ORIGIN_LAT_DEG = 47.397743
SIH_ORIGIN_LON_DEG = 8.545594
SIH_ORIGIN_ALT_M = 489.4

# PX4 WMM-2020 tables at the SIH origin (corners lat 40/50, lon 0/10, bilinear):
# declination 218/580/157/660, inclination 9581/9746/11387/11493 (1e-4 rad),
# strength 4513/4593/4860/4911 (1e-4 G).
MAG_DECLINATION_RAD = 0.0571362
MAG_INCLINATION_RAD = 1.1020736
MAG_STRENGTH_GAUSS = 0.4819733

EARTH_RADIUS_M = 6371000.0  # PX4 lib/geo CONSTANTS_RADIUS_OF_EARTH

# International Standard Atmosphere, troposphere (PX4 sensors: SENS_BARO_QNH 1013.25 hPa)
ISA_P0_PA = 101325.0
ISA_T0_K = 288.15
ISA_LAPSE_K_M = 0.0065
ISA_EXPONENT = 5.255877  # g0 M / (R L)


@dataclass(frozen=True)
class SensorConfig:
    """Validated ``sensors:`` block (see the module docstring for meaning and units)."""

    gyro_noise_rad_s: tuple[float, float, float] = (8.7e-4, 8.7e-4, 8.7e-4)
    gyro_bias_rad_s: tuple[float, float, float] = (1.0e-3, -7.0e-4, 5.0e-4)
    accel_noise_m_s2: tuple[float, float, float] = (0.044, 0.044, 0.044)
    accel_bias_m_s2: tuple[float, float, float] = (0.04, -0.03, 0.05)
    mag_noise_gauss: float = 0.002
    baro_noise_hpa: float = 0.012
    gps_noise_m: float = 0.5
    gps_correlation_time_s: float = 90.0
    gps_white_noise_m: float = 0.03
    gps_vel_noise_m_s: float = 0.05
    gps_rate_hz: float = 10.0
    mag_rate_hz: float = 100.0
    baro_rate_hz: float = 50.0
    home_lat_deg: float = SIH_ORIGIN_LAT_DEG
    home_lon_deg: float = SIH_ORIGIN_LON_DEG
    home_alt_m: float = SIH_ORIGIN_ALT_M
    seed: int = 0

    @classmethod
    def from_mapping(cls, data: Mapping[str, Any] | None, path: str = "<memory>") -> "SensorConfig":
        """Validate a ``sensors:`` mapping; errors read ``file: sensors.key: expected``."""
        data = dict(data or {})
        known = {f.name: f for f in fields(cls)}
        for k in data:
            if k not in known:
                raise ParamsError(path, f"sensors.{k}", f"unknown key (allowed: {', '.join(sorted(known))})")
        out: dict[str, Any] = {}
        for name, value in data.items():
            key = f"sensors.{name}"
            default = known[name].default
            if isinstance(default, tuple):
                if (not isinstance(value, (list, tuple)) or len(value) != 3
                        or not all(_is_num(v) for v in value)):
                    raise ParamsError(path, key, f"expected 3 numbers (x, y, z in FRD), got {value!r}")
                vals = tuple(float(v) for v in value)
                if not all(np.isfinite(vals)):
                    raise ParamsError(path, key, f"expected finite numbers, got {value!r}")
                if name.endswith("_noise_rad_s") or name.endswith("_noise_m_s2"):
                    if any(v < 0 for v in vals):
                        raise ParamsError(path, key, f"expected noise σ >= 0, got {value!r}")
                out[name] = vals
            elif name == "seed":
                if isinstance(value, bool) or not isinstance(value, int) or value < 0:
                    raise ParamsError(path, key, f"expected a non-negative integer, got {value!r}")
                out[name] = int(value)
            else:
                if not _is_num(value) or not np.isfinite(float(value)):
                    raise ParamsError(path, key, f"expected a finite number, got {value!r}")
                v = float(value)
                if name.endswith("_rate_hz") and not v > 0:
                    raise ParamsError(path, key, f"expected > 0, got {v:g}")
                if name == "gps_correlation_time_s" and v < 0:
                    raise ParamsError(path, key, f"expected a time >= 0 (0 = white noise), got {v:g}")
                if ("noise" in name) and v < 0:
                    raise ParamsError(path, key, f"expected noise σ >= 0, got {v:g}")
                if name == "home_lat_deg" and not -90.0 < v < 90.0:
                    raise ParamsError(path, key, f"expected a latitude in (-90, 90), got {v:g}")
                if name == "home_lon_deg" and not -180.0 <= v <= 180.0:
                    raise ParamsError(path, key, f"expected a longitude in [-180, 180], got {v:g}")
                out[name] = v
        return cls(**out)

    @classmethod
    def from_params(cls, vp: Any) -> "SensorConfig":
        """From a :class:`~twin_nodes.vehicle.params.VehicleParams` (its ``sensors`` block)."""
        return cls.from_mapping(getattr(vp, "sensors", None), getattr(vp, "source", "<memory>"))


def _is_num(v: Any) -> bool:
    return isinstance(v, (int, float)) and not isinstance(v, bool)


# --------------------------------------------------------------------------- pure models


def mag_field_ned_gauss() -> np.ndarray:
    """Earth field at the SIH origin, NED [G] (PX4 ``sensor_mag_sim``: Rz(dec) Ry(-inc) [B, 0, 0])."""
    ci = np.cos(MAG_INCLINATION_RAD)
    return MAG_STRENGTH_GAUSS * np.array([ci * np.cos(MAG_DECLINATION_RAD),
                                          ci * np.sin(MAG_DECLINATION_RAD),
                                          np.sin(MAG_INCLINATION_RAD)])


def isa_pressure_pa(alt_amsl_m: np.ndarray) -> np.ndarray:
    """ISA static pressure [Pa] at altitude [m AMSL] (troposphere)."""
    h = np.asarray(alt_amsl_m, dtype=float)
    return ISA_P0_PA * (1.0 - ISA_LAPSE_K_M * h / ISA_T0_K) ** ISA_EXPONENT


def isa_altitude_m(pressure_pa: np.ndarray) -> np.ndarray:
    """Inverse of :func:`isa_pressure_pa`: pressure altitude [m] (QNH 1013.25 hPa)."""
    p = np.asarray(pressure_pa, dtype=float)
    return ISA_T0_K / ISA_LAPSE_K_M * (1.0 - (p / ISA_P0_PA) ** (1.0 / ISA_EXPONENT))


def isa_temperature_c(alt_amsl_m: np.ndarray) -> np.ndarray:
    """ISA temperature [°C] at altitude [m AMSL]."""
    return ISA_T0_K - ISA_LAPSE_K_M * np.asarray(alt_amsl_m, dtype=float) - 273.15


def reproject_ne_to_latlon(north_m: np.ndarray, east_m: np.ndarray, lat0_deg: float,
                           lon0_deg: float) -> tuple[np.ndarray, np.ndarray]:
    """Local north/east [m] about (lat0, lon0) -> lat/lon [deg].

    PX4's azimuthal equidistant ``MapProjection::reproject`` (lib/geo), so a
    position sent by GPS comes back through PX4's own ``project`` unchanged."""
    x = np.asarray(north_m, dtype=float) / EARTH_RADIUS_M
    y = np.asarray(east_m, dtype=float) / EARTH_RADIUS_M
    lat0 = np.radians(lat0_deg)
    lon0 = np.radians(lon0_deg)
    c = np.hypot(x, y)
    sin_c, cos_c = np.sin(c), np.cos(c)
    safe_c = np.where(c > 0.0, c, 1.0)
    lat = np.where(c > 0.0, np.arcsin(cos_c * np.sin(lat0) + x * sin_c * np.cos(lat0) / safe_c), lat0)
    lon = np.where(c > 0.0, lon0 + np.arctan2(y * sin_c, c * np.cos(lat0) * cos_c - x * np.sin(lat0) * sin_c),
                   lon0)
    return np.degrees(lat), np.degrees(lon)


def project_latlon_to_ne(lat_deg: np.ndarray, lon_deg: np.ndarray, lat0_deg: float,
                         lon0_deg: float) -> tuple[np.ndarray, np.ndarray]:
    """lat/lon [deg] -> local north/east [m] about (lat0, lon0) (PX4 ``MapProjection::project``)."""
    lat = np.radians(np.asarray(lat_deg, dtype=float))
    lon = np.radians(np.asarray(lon_deg, dtype=float))
    lat0 = np.radians(lat0_deg)
    lon0 = np.radians(lon0_deg)
    cos_d_lon = np.cos(lon - lon0)
    arg = np.clip(np.sin(lat0) * np.sin(lat) + np.cos(lat0) * np.cos(lat) * cos_d_lon, -1.0, 1.0)
    c = np.arccos(arg)
    k = np.where(np.abs(c) > 0.0, c / np.where(np.sin(c) == 0.0, 1.0, np.sin(c)), 1.0)
    north = k * (np.cos(lat0) * np.sin(lat) - np.sin(lat0) * np.cos(lat) * cos_d_lon) * EARTH_RADIUS_M
    east = k * np.cos(lat) * np.sin(lon - lon0) * EARTH_RADIUS_M
    return north, east


@dataclass(frozen=True)
class GpsFix:
    """One GPS sample: position [deg, deg, m AMSL] and NED velocity [m/s]."""

    lat_deg: float
    lon_deg: float
    alt_m: float
    vel_ned_m_s: np.ndarray
    eph_m: float
    epv_m: float

    @property
    def ground_speed_m_s(self) -> float:
        return float(np.hypot(self.vel_ned_m_s[0], self.vel_ned_m_s[1]))

    @property
    def course_rad(self) -> float:
        """Course over ground [rad, 0..2π from North, clockwise]."""
        return float(np.arctan2(self.vel_ned_m_s[1], self.vel_ned_m_s[0]) % (2.0 * np.pi))


class SensorModel:
    """Measured sensor values from the twin's true state (ENU/FLU in, PX4 frames out).

    >>> sm = SensorModel(SensorConfig(), gravity_m_s2=9.80665)
    >>> acc_frd, gyro_frd = sm.imu(np.array([0, 0, 9.80665]), np.zeros(3))   # at rest: z ≈ -g
    """

    def __init__(self, config: SensorConfig | None = None, gravity_m_s2: float = G_STANDARD_M_S2,
                 rng: np.random.Generator | None = None):
        self.config = config or SensorConfig()
        self.gravity_m_s2 = float(gravity_m_s2)
        self.rng = rng if rng is not None else np.random.default_rng(self.config.seed)
        c = self.config
        self._gyro_bias = np.array(c.gyro_bias_rad_s, dtype=float)
        self._gyro_sigma = np.array(c.gyro_noise_rad_s, dtype=float)
        self._acc_bias = np.array(c.accel_bias_m_s2, dtype=float)
        self._acc_sigma = np.array(c.accel_noise_m_s2, dtype=float)
        self._mag_enu = frames.ned_to_enu(mag_field_ned_gauss())
        self._gps_err_ned: np.ndarray | None = None  # the correlated GPS position error [m]

    def _noise(self, sigma: np.ndarray | float, n: int = 3) -> np.ndarray:
        return self.rng.standard_normal(n) * sigma

    def imu(self, specific_force_flu: np.ndarray, rates_flu: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Accelerometer [m/s², specific force] and gyro [rad/s], both body FRD."""
        acc = frames.flu_to_frd(np.asarray(specific_force_flu, dtype=float))
        gyro = frames.flu_to_frd(np.asarray(rates_flu, dtype=float))
        return (acc + self._acc_bias + self._noise(self._acc_sigma),
                gyro + self._gyro_bias + self._noise(self._gyro_sigma))

    def mag(self, q_enu_flu: np.ndarray) -> np.ndarray:
        """Magnetometer [G], body FRD: the NED Earth field seen in the body frame."""
        return self.mag_from_rotmat(frames.quat_to_rotmat(np.asarray(q_enu_flu, dtype=float)))

    def mag_from_rotmat(self, r_enu_flu: np.ndarray) -> np.ndarray:
        """:meth:`mag` from the attitude as a rotation matrix (``v_enu = R @ v_flu``)."""
        field_flu = np.asarray(r_enu_flu, dtype=float).T @ self._mag_enu
        return frames.flu_to_frd(field_flu) + self._noise(self.config.mag_noise_gauss)

    def baro(self, z_enu_m: float) -> tuple[float, float, float]:
        """``(abs_pressure_hpa, pressure_alt_m, temperature_c)`` at height ``z_enu_m`` above home.

        The pressure altitude is that of the *measured* (noisy) pressure."""
        alt = self.config.home_alt_m + float(z_enu_m)
        p_pa = float(isa_pressure_pa(alt)) + 100.0 * float(self._noise(self.config.baro_noise_hpa, 1)[0])
        return p_pa / 100.0, float(isa_altitude_m(p_pa)), float(isa_temperature_c(alt))

    def gps_position_error_ned(self, dt_s: float | None = None) -> np.ndarray:
        """The next GPS position error [m, NED]: Gauss-Markov (σ ``gps_noise_m``, correlation time
        ``gps_correlation_time_s``, stationary from the first sample) + white ``gps_white_noise_m``.

        ``dt_s``: time since the previous fix (default ``1 / gps_rate_hz``); a correlation time of
        0 gives white noise of σ ``gps_noise_m`` (the model before issue 14)."""
        c = self.config
        dt = 1.0 / c.gps_rate_hz if dt_s is None else max(float(dt_s), 0.0)
        if c.gps_correlation_time_s <= 0.0:
            err = self._noise(c.gps_noise_m)
        elif self._gps_err_ned is None:
            err = self._noise(c.gps_noise_m)  # stationary start
        else:
            a = float(np.exp(-dt / c.gps_correlation_time_s))
            err = a * self._gps_err_ned + self._noise(c.gps_noise_m * np.sqrt(max(1.0 - a * a, 0.0)))
        self._gps_err_ned = err
        return err + self._noise(c.gps_white_noise_m)

    def gps(self, position_enu_m: np.ndarray, velocity_enu_m_s: np.ndarray, dt_s: float | None = None) -> GpsFix:
        """A GPS fix from the true ENU position/velocity about home (``dt_s``: time since the last
        fix, default ``1 / gps_rate_hz``; the link calls this once per GPS period)."""
        c = self.config
        p_ned = frames.enu_to_ned(np.asarray(position_enu_m, dtype=float)) + self.gps_position_error_ned(dt_s)
        v_ned = frames.enu_to_ned(np.asarray(velocity_enu_m_s, dtype=float)) + self._noise(c.gps_vel_noise_m_s)
        lat, lon = reproject_ne_to_latlon(p_ned[0], p_ned[1], c.home_lat_deg, c.home_lon_deg)
        sigma = float(np.hypot(c.gps_noise_m, c.gps_white_noise_m))
        return GpsFix(lat_deg=float(lat), lon_deg=float(lon), alt_m=c.home_alt_m - float(p_ned[2]),
                      vel_ned_m_s=v_ned,
                      # PX4 takes eph/epv as accuracies [m] (×100 on the wire); floor at 0.1 m
                      eph_m=max(float(np.sqrt(2.0) * sigma), 0.1),
                      epv_m=max(sigma, 0.1))
