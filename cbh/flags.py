"""Quality flags of a frame pair: one enumeration with FIXED bit values.

Results carry flag *names* (``PairResult.flags``, a list of str); MCAP, CSV/Parquet and the
NetCDF ``quality_flag`` variable (``flag_masks`` / ``flag_meanings``) all use these bits, so a
file's bits never depend on which flags it happens to contain. New flags are appended with the
next free bit; a bit is never reused or renumbered.
"""
from __future__ import annotations

import enum
from typing import Iterable

__all__ = ["Flag", "flag_bits", "flag_names", "check_flags", "flag_meaning", "INVALIDATING", "HIDDEN_OFFSET_SHARE"]


class Flag(enum.IntFlag):
    """Quality flags (bit values are part of the file formats: never change them)."""

    time_unknown = 1 << 0  # the pair has no capture time (sun masks and motion unavailable)
    sun_glare = 1 << 1  # a saturated sun/glare region was masked
    cover_incomplete = 1 << 2  # the layers' covers add up to less than the cloud fraction
    few_points = 1 << 3  # too few triangulated points for a layer
    clear_sky = 1 << 4  # no cloud in the usable sky
    overcast_no_texture = 1 << 5  # cloud everywhere but too little texture to match
    geometry_mismatch = 1 << 6  # the correspondences disagree with the station geometry
    sun_misaligned = 1 << 7  # the detected sun is off the predicted sun by more than the tolerance
    time_jump = 1 << 8  # a frame's time jumped against the other camera or the wall clock
    clock_offset = 1 << 9  # the cameras' clocks differ by more than the pairing tolerance
    exposure_mismatch = 1 << 10  # the cameras' photometric difference is large (corrected, reported)
    identical_images = 1 << 11  # both cameras delivered the same image
    below_range = 1 << 12  # much of the measured cloud sits on the sweep's lowest plane: cloud at or below its floor
    cloud_unmatched = 1 << 13  # most of camera 1's cloud found no height: the layers describe only the matched part
    underexposed = 1 << 14  # a camera's sky is too dark for its colours to be read: cloud masks and cover unreliable
    camera_mismatch = 1 << 15  # a network camera disagrees with the others' geometry and was left out (diagnostics mismatched_cameras); the others carry the result
    camera_missing = 1 << 16  # a network camera delivered no frame: the result is from the cameras present
    clock_unknown = 1 << 17  # the matches disagree with the geometry, or are too few to judge it, while the cameras' clock offset, which could explain it or hide behind it, is not known yet (e.g. a run's first pair): layers not valid
    clock_too_far = 1 << 19  # the cameras' clocks differ by more than the sky's motion could be carried over on this pair (the sky maps found no match at the running offset, or the carry's noise, frames captured off their stamps included, is as large as a layer's parallax): layers not valid
    overexposed = 1 << 20  # half a camera's sky or more has two channels at white: cloud masks and cover unreliable
    night = 1 << 18  # the sun more than 6 deg below the horizon and a camera's sky too dark to read: no cloud can be told, no layer reported, no geometry judged


#: Flags whose layers must not be reported as valid (exported with the flag, left out of
#: "latest layers").
INVALIDATING = frozenset({"geometry_mismatch", "identical_images", "below_range", "clock_unknown", "clock_too_far",
                          "night"})

#: ``clock_unknown`` while camera 2's offset was never measured: the largest share of a layer's
#: parallax that an offset the geometry check cannot see may move (the real hour's 10 % bar).
HIDDEN_OFFSET_SHARE = 0.1


_MEANING = {
    "time_unknown": "the pair has no capture time: no sun mask beyond the saturated disc, no motion",
    "sun_glare": "a saturated sun or glare region was masked",
    "cover_incomplete": "the layers' covers add up to less than the cloud fraction",
    "few_points": "too few triangulated points for a layer",
    "clear_sky": "no cloud in the usable sky",
    "overcast_no_texture": "cloud everywhere but too little texture to match",
    "geometry_mismatch": "the matches disagree with the station geometry (a camera moved, turned or was "
                         "swapped, or its calibration is off), and no clock offset explains it",
    "sun_misaligned": "the sun seen in a camera is off the predicted sun by more than the tolerance",
    "time_jump": "a frame's time jumped against the other camera or the wall clock",
    "clock_offset": "the cameras' clocks differ (the estimate is taken out of the result)",
    "exposure_mismatch": "the cameras' photometric difference is large (corrected, reported)",
    "identical_images": "both cameras delivered the same image",
    "below_range": "much of the cloud sits on the lowest height searched: cloud at or below it",
    "cloud_unmatched": "most of the cloud found no height: the layers describe only the matched part",
    "underexposed": "a camera's sky is too dark for its colours to be read",
    "overexposed": "half a camera's sky or more has two colour channels at the camera's white level: its "
                   "colours are lost, so cloud cannot be told from clear sky there",
    "camera_mismatch": "a network camera disagrees with the others' geometry and was left out",
    "camera_missing": "a network camera delivered no frame",
    "night": "the sun is more than 6° below the horizon and the sky too dark to read: cloud cannot be told from "
             "clear sky, so no layer is reported and the geometry is not judged",
    "clock_too_far": "the cameras' clocks differ by more than the sky's motion could be carried over on this pair: "
                     "the clouds moved too far between the two captures for camera 2's view to be matched at camera "
                     "1's time (the sky maps found no match at the running offset, or carrying it there blurs a layer by as much as its "
                     "parallax, as frames captured off their stamps do), so no layer is valid",
    "clock_unknown": "the matches disagree with the geometry, or are too few to judge it, while the cameras' "
                     "clock offset, which could explain a disagreement or hide behind too few matches, is not known "
                     "yet (or, resumed from a recording, not yet taken out: a run's first pair has no motion to "
                     "carry a camera with); or, while it is not known, an offset the geometry check cannot see "
                     "would move a layer by more than a tenth (a wind along the baseline, or a slow one over a "
                     "high deck: diagnostics clock_hidden_share; a station whose clocks are right states "
                     "clock_offset_s)",
}


def flag_meaning(name: str) -> str:
    """What a flag means, in one line (for people: the viewer's flag panel, summaries)."""
    return _MEANING.get(name, name)


def check_flags(names: Iterable[str]) -> list[str]:
    """The names, validated against :class:`Flag` (ValueError naming an unknown flag)."""
    out = []
    for n in names:
        if n not in Flag.__members__:
            raise ValueError(f"unknown quality flag {n!r} (known: {', '.join(Flag.__members__)})")
        out.append(n)
    return out


def flag_bits(names: Iterable[str]) -> int:
    """Flag names → integer bit mask (fixed bits of :class:`Flag`)."""
    bits = 0
    for n in check_flags(names):
        bits |= int(Flag[n])
    return bits


def flag_names(bits: int) -> list[str]:
    """Integer bit mask → flag names, in bit order."""
    return [f.name for f in Flag if int(bits) & int(f)]
