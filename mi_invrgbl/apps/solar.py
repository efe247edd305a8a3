"""Where the sun is: elevation and azimuth from date, time and place.

``relight --time`` turns a clock time into a sun direction with the NOAA
"General Solar Position" formulas (equation of time and declination from a
Fourier series in the fractional year), accurate to a few tenths of a degree
between the polar circles, which is far below what shading can show.

Conventions:

* :func:`solar_position` returns the compass azimuth (degrees from north,
  clockwise: east = 90) and the elevation above the horizon (no refraction).
* Scenes use the project's world frame, z up, with azimuths measured from +x
  towards +y (counter-clockwise seen from above). :func:`world_azimuth`
  converts with ``north``, the world azimuth of geographic north: with the
  default 90, +x points east and +y north (east-north-up).

The default place is Karlsruhe, where KITTI was recorded (49.01 N, 8.40 E).
"""

from __future__ import annotations

import datetime as _dt
import math

from ..errors import UserError

#: KITTI's city: latitude, longitude (degrees) and summer-time UTC offset (hours).
KARLSRUHE = (49.01, 8.40, 2.0)


def solar_position(when: _dt.datetime, latitude: float, longitude: float) -> tuple[float, float]:
    """(elevation, compass azimuth) of the sun in degrees.

    ``when`` must carry its time zone (``tzinfo``); ``longitude`` is positive east.
    """
    if when.tzinfo is None:
        raise ValueError("solar_position needs a time zone-aware datetime")
    utc = when.astimezone(_dt.timezone.utc)
    day = utc.timetuple().tm_yday
    hours = utc.hour + utc.minute / 60.0 + utc.second / 3600.0
    days_in_year = 366 if _is_leap(utc.year) else 365
    g = 2.0 * math.pi / days_in_year * (day - 1 + (hours - 12.0) / 24.0)
    eqtime = 229.18 * (0.000075 + 0.001868 * math.cos(g) - 0.032077 * math.sin(g)
                       - 0.014615 * math.cos(2 * g) - 0.040849 * math.sin(2 * g))
    decl = (0.006918 - 0.399912 * math.cos(g) + 0.070257 * math.sin(g)
            - 0.006758 * math.cos(2 * g) + 0.000907 * math.sin(2 * g)
            - 0.002697 * math.cos(3 * g) + 0.00148 * math.sin(3 * g))
    true_solar_minutes = hours * 60.0 + eqtime + 4.0 * longitude
    hour_angle = math.radians(true_solar_minutes / 4.0 - 180.0)
    lat = math.radians(latitude)
    cos_zenith = (math.sin(lat) * math.sin(decl)
                  + math.cos(lat) * math.cos(decl) * math.cos(hour_angle))
    elevation = 90.0 - math.degrees(math.acos(max(-1.0, min(1.0, cos_zenith))))
    # Azimuth from south (positive west), then turned to a compass bearing.
    from_south = math.atan2(math.sin(hour_angle),
                            math.cos(hour_angle) * math.sin(lat) - math.tan(decl) * math.cos(lat))
    azimuth = (math.degrees(from_south) + 180.0) % 360.0
    return elevation, azimuth


def world_azimuth(compass_azimuth: float, north: float = 90.0) -> float:
    """World azimuth (from +x towards +y) of a compass bearing; ``north`` = world azimuth of north."""
    return (north - compass_azimuth + 180.0) % 360.0 - 180.0


def _is_leap(year: int) -> bool:
    return year % 4 == 0 and (year % 100 != 0 or year % 400 == 0)


def parse_time(text: str, date: str | None = None, utc_offset: float | None = None) -> _dt.datetime:
    """A zone-aware datetime from ``--time`` (ISO ``2024-06-21T15:30[+02:00]`` or ``15:30``).

    A bare clock time takes its day from ``date`` (``YYYY-MM-DD``, default
    2024-06-21). Without a zone in the text, ``utc_offset`` hours apply
    (default: Karlsruhe summer time, UTC+2).
    """
    text = text.strip()
    try:
        if "T" in text or " " in text or (len(text) >= 10 and text[4] == "-"):
            when = _dt.datetime.fromisoformat(text.replace(" ", "T"))
        else:
            day = _dt.date.fromisoformat(date) if date else _dt.date(2024, 6, 21)
            clock = _dt.time.fromisoformat(text)
            when = _dt.datetime.combine(day, clock)
    except ValueError:
        raise UserError("--time: cannot read '%s' (use HH:MM or YYYY-MM-DDTHH:MM[+HH:MM])"
                        % text) from None
    if when.tzinfo is None:
        offset = KARLSRUHE[2] if utc_offset is None else float(utc_offset)
        when = when.replace(tzinfo=_dt.timezone(_dt.timedelta(hours=offset)))
    return when
