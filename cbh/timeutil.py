"""UTC times in and out: the one place cbh reads a time (policy: docs/conventions.md).

- :func:`parse_utc`: ISO 8601 text (or a ``datetime``, e.g. from TOML) → aware UTC datetime.
  A time **without a zone is an error** (never guessed to be UTC or local): the message names
  the expected form, e.g. ``2024-06-21T14:00:00Z``.
- :func:`time_from_name`: the UTC stamp in a file name. File names are the one exception to
  the rule: a stamp in a file name is UTC whether or not it ends in ``Z`` (the conventions
  page declares it), because cameras and the simulator write names without zones.
- :func:`parse_time_header`: a camera's ``X-Timestamp`` header (Unix seconds or ISO 8601 with
  a zone); None when it is absent or cannot be read (the receive time is used instead).
- :func:`format_utc`: aware datetime → ``2024-06-21T14:00:00Z`` (``unknown`` for None).
"""
from __future__ import annotations

import re
from datetime import datetime, timedelta, timezone

from cbh.errors import InputError

__all__ = ["parse_utc", "time_from_name", "parse_time_header", "format_utc", "wait_until", "EXAMPLE"]

#: The form every message asks for.
EXAMPLE = "2024-06-21T14:00:00Z"


def parse_utc(value, what: str = "time", error: type[Exception] = InputError) -> datetime:
    """ISO 8601 text (or a datetime) with a zone → timezone-aware UTC datetime.

    Parameters
    ----------
    value : str or datetime
        E.g. ``"2015-10-29T04:58:01Z"``, ``"2015-10-29T06:58:01+02:00"``; a TOML offset
        date-time arrives as an aware ``datetime``.
    what : str
        Names the value in the error message (a key path or an option).
    error : exception class
        Raised on bad input (default :class:`cbh.errors.InputError`; config readers pass
        :class:`cbh.errors.ConfigError`).

    Raises
    ------
    error
        Not a time, or a time without a zone (``Z`` or ``±HH:MM``).

    >>> parse_utc("2015-10-29T06:58:01+02:00").isoformat()
    '2015-10-29T04:58:01+00:00'
    """
    if isinstance(value, datetime):
        t = value
    elif isinstance(value, str):
        text = value.strip()
        if text[-1:] in ("Z", "z"):
            text = text[:-1] + "+00:00"
        try:
            t = datetime.fromisoformat(text)
        except ValueError:
            raise error(f"{what}: not an ISO 8601 time: {value!r} (expected e.g. {EXAMPLE})") from None
    else:
        raise error(f"{what}: expected a UTC time like {EXAMPLE}, got {value!r}")
    if t.tzinfo is None:
        raise error(f"{what}: time {str(value)!r} has no zone; cbh never guesses one: "
                    f"end it with Z for UTC or give an offset (expected e.g. {EXAMPLE})")
    return t.astimezone(timezone.utc)


_NAME_TIME = re.compile(
    r"(?<!\d)(\d{4})-?(\d{2})-?(\d{2})[T_ \-]?(\d{2})[:\-]?(\d{2})[:\-]?(\d{2})(?:[.,](\d{1,9}))?(Z)?(?!\d)"
    # a zone right after the time: UTC, UTC+1, UTCp1 / UTCm2 (the "+"/"-" spelled out, as IP cameras
    # name files where "+" is awkward), UTC+05:30, or an ISO offset +01:00 / +0100
    r"(?:[_\-]?UTC(?:([+\-pm])(\d{1,2})(?::?(\d{2}))?)?(?![a-z])|([+\-])(\d{2}):(\d{2})(?!\d)|(\+)(\d{2})(\d{2})(?!\d))?",
    re.IGNORECASE,
)


def time_from_name(name: str) -> datetime | None:
    """UTC time stamped in a file name, or None.

    The first ``YYYY-MM-DD[T_ -]HH:MM:SS[.fff][Z]`` in the name, with or without the ``-``
    and ``:`` separators, read as UTC (with or without ``Z``: docs/conventions.md), unless a
    zone follows the time: ``UTC+1`` / ``UTCp1`` / ``UTCm2`` / ``UTC+05:30`` or ``+01:00`` / ``+0100``
    (VIVOTEK cameras name files ``FE3_Image_20160901_100000_UTCp1.jpg``: 09:00:00 UTC).

    >>> time_from_name("cam1_20151029T045801.250Z.jpg").isoformat()
    '2015-10-29T04:58:01.250000+00:00'
    >>> time_from_name("FE3_Image_20160901_100000_UTCp1.jpg").isoformat()
    '2016-09-01T09:00:00+00:00'
    """
    m = _NAME_TIME.search(str(name))
    if not m:
        return None
    y, mo, d, h, mi, s, frac = m.groups()[:7]
    try:
        t = datetime(int(y), int(mo), int(d), int(h), int(mi), int(s), tzinfo=timezone.utc)
    except ValueError:
        return None
    if frac:
        t += timedelta(microseconds=int(round(int(frac) / 10 ** len(frac) * 1e6)))
    return t - _name_zone_offset(m.groups()[8:])


def _name_zone_offset(groups) -> timedelta:
    """The zone offset a file name states after its time (0 for none, ``Z`` or plain ``UTC``)."""
    sign, hh, mm, *iso = groups  # (a "-HHMM" without a colon is not read: a frame counter looks alike)
    for k in (0, 3):
        if iso[k]:
            sign, hh, mm = iso[k:k + 3]
    if not sign:
        return timedelta(0)
    off = timedelta(hours=int(hh), minutes=int(mm or 0))
    return -off if sign.lower() in ("-", "m") else off


def parse_time_header(value: str | None) -> datetime | None:
    """A camera's time header: Unix seconds (``1446094681.25``) or ISO 8601 with a zone; None if
    absent or unreadable (a header without a zone is unreadable: the receive time is used)."""
    if not value:
        return None
    value = value.strip()
    try:
        return datetime.fromtimestamp(float(value), tz=timezone.utc)
    except (ValueError, OverflowError, OSError):
        pass
    try:
        return parse_utc(value, "X-Timestamp")
    except InputError:
        return None


def format_utc(t: datetime | None) -> str:
    """``2024-06-21T14:00:00Z`` (microseconds kept when non-zero); ``unknown`` for None."""
    if t is None:
        return "unknown"
    return t.astimezone(timezone.utc).isoformat().replace("+00:00", "Z")


def wait_until(t_monotonic: float, timeout_s: float) -> bool:
    """Sleep until ``time.monotonic()`` reaches ``t_monotonic`` if that comes within ``timeout_s``
    [s] and return True; otherwise sleep ``timeout_s`` and return False (a source's pacing)."""
    import time

    wait = t_monotonic - time.monotonic()
    if wait > timeout_s:
        time.sleep(max(timeout_s, 0.0))
        return False
    if wait > 0:
        time.sleep(wait)
    return True
