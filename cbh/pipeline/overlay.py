"""A camera's on-screen text (its clock, its name) stamped onto the sky, found in one frame.

IP cameras write the date, the time and their name into every frame (the OSD), drawn by the
camera after the optics. For legibility it is white with a black outline or shadow, or white on
a black banner. Where the lens's image circle is wider than the frame, or the overlay sits
inside the circle, the text lies on the sky. Left there, it is white cloud to the segmentation,
and its white, at the encoder's 255, a spike in the histogram above a camera's own clip (235):
on 60 randomized skies whose cameras stamp their clock (``eval_random.py --overlays --seed
19300``), 21 pairs' flags differed from the same skies unstamped (``sun_glare`` lost, clear skies
``cloud_unmatched``), and a clear sky under a banner gave three spurious layers (19358).

What tells it from the sky (physics): the lens blurs every scene edge over a couple of pixels,
and nothing in the sky is near black beside near white. The OSD is drawn onto the pixel grid
after the lens: near-white strokes within a pixel or two of near-black outline, in a row of
glyphs of one height along the frame's rows, each glyph crossed by several strokes. A skyline
(dark roofs and trees against bright sky) has the black-beside-white edges but not the
strokes: a roof's edge is one solid band, a tree line is as tall as it is ragged.

Method (:func:`overlay_text`): "hard" pixels are those whose 3 × 3 neighbourhood spans from
at most ``BLACK_DN`` to at least ``WHITE_DN`` of luma. Their connected components of a
text's height (glyphs) are chained along the rows to those of a like height on the same rows
at most ``_GLYPH_GAP`` of their height away (:func:`text_lines`); the chains are text lines when they are at most
``MAX_HEIGHT_FRAC`` of the frame tall, at least ``MIN_ASPECT`` times as wide as tall, and
their middle rows step from black to white at least ``MIN_STROKES_PER_HEIGHT`` times per
height of width (:func:`strokes_per_height`; each glyph has two or more; a solid band none),
and their hard pixels fill at least ``MIN_FILL`` of the box (a glyph's strokes, each with its
outline, cross each of its columns several times: 0.19–0.7 of the box at 480 px, 0.15 for large
shadowed text at 960 px whose strokes are wider than the 3 × 3 band; a roofline, a row of tree
crowns or a city's blocks is one contour, the band a few pixels thick: 0.04–0.07 where, on
randomized skylines, they stepped from black to white as often as text). A shorter chain right above or
below a line (the camera's name over its clock) is text too. Each line's box, grown by a quarter of its
height (the outline, the strokes' blur), is the overlay, with the near-black pixels up to a
height beyond it (a banner's margin: masking the whole height would take sky the text does not
hide, and cost a thin layer's matches in camera 2).

Limits: text without an outline, shadow or banner (white on sky) has no black beside it and is
not found; nor is text smaller than ``MIN_HEIGHT_PX`` at working size.
"""
from __future__ import annotations

import cv2
import numpy as np

from cbh.pipeline.ccl import components_with_stats
from cbh.pipeline.peaks import weighted_median

__all__ = ["overlay_text", "search_area", "BLACK_DN", "WHITE_DN"]

BLACK_DN = 70  # the outline's luma at most this (0, or 16 in limited-range video, plus JPEG's ringing) [DN]
WHITE_DN = 170  # the strokes' luma at least this (255 or 235, less the working size's averaging) [DN]
MIN_HEIGHT_PX = 6  # smallest text line found, outline included, at working size [px]
MAX_HEIGHT_FRAC = 0.08  # tallest text line, as a share of the frame's height [1]
MIN_ASPECT = 3.0  # a text line of at least three glyphs is this many heights wide [1]
MIN_FILL = 0.1  # hard pixels fill at least this of a line's box (text 0.15–0.7 measured; skylines that step as text does 0.04–0.07) [1]
MIN_STROKES_PER_HEIGHT = 0.8  # strokes crossed along the middle rows per height of width (text 1.0–3.4 measured at 480 and 960 px; a glyph has 2–4 per 0.6 heights) [1]


_GLYPH_GAP = 1.0  # glyphs of one line are at most this many heights apart (a space between words, a colon between digits) [1]
_MAX_GLYPHS = 600  # glyph boxes chained at most (pairwise: 600² pairs, a few MB), in raster order: a frame with text has tens to a hundred


def search_area(circle: np.ndarray) -> np.ndarray:
    """Where a camera's text is looked for: its image circle (H, W) bool less a 3 px rim, whose
    step from the black outside to a bright sky is a hard edge all round."""
    return cv2.erode(np.asarray(circle, bool).view(np.uint8), np.ones((7, 7), np.uint8)) > 0


def hard_edges(luma: np.ndarray) -> np.ndarray:
    """(H, W) uint8, 1 where a pixel's 3 × 3 neighbourhood holds luma ≤ ``BLACK_DN`` and ≥ ``WHITE_DN``."""
    k = np.ones((3, 3), np.uint8)
    hi = cv2.dilate(luma, k)
    lo = cv2.erode(luma, k)
    return ((hi >= WHITE_DN) & (lo <= BLACK_DN)).view(np.uint8)


def strokes_per_height(luma_box: np.ndarray) -> float:
    """Strokes crossed along the middle half of a box's rows, per height of its width: the median
    over those rows of the steps from near black (≤ ``BLACK_DN``) to near white (≥ ``WHITE_DN``),
    the grey levels between skipped (JPEG's and the working size's blur), times height / width.
    A glyph's outline and stroke give one such step per stroke (2–4 per glyph, a glyph about
    0.6 heights wide); a roof's edge, along its rows, none."""
    h, w = luma_box.shape
    mid = luma_box[h // 4: max(h - h // 4, h // 4 + 1)]
    cls = np.where(mid <= BLACK_DN, -1, np.where(mid >= WHITE_DN, 1, 0)).astype(np.int8)
    steps = []
    for row in cls:
        row = row[row != 0]
        steps.append(np.count_nonzero((row[1:] == 1) & (row[:-1] == -1)))
    return float(np.median(steps)) * h / max(w, 1)


def overlay_text(image_bgr: np.ndarray, inside: np.ndarray | None = None) -> np.ndarray | None:
    """The camera's on-screen text lines in one frame (see the module doc).

    Parameters
    ----------
    image_bgr : ndarray, shape (H, W, 3), uint8
        The frame (any size; the pipeline passes its working size).
    inside : ndarray, shape (H, W), bool, optional
        Where to look: the image circle less its rim (:func:`search_area`). The rim's
        step from the black outside to a bright sky is a hard edge all round, which would merge
        with the glyphs of a line that crosses it; text outside the circle hides no sky.

    Returns
    -------
    ndarray, shape (H, W), bool, or None
        True on each text line's box, grown by a quarter of its height (at least 2 px), and the
        near-black pixels up to a height beyond it; None when there is none.
    """
    luma = cv2.cvtColor(np.ascontiguousarray(image_bgr), cv2.COLOR_BGR2GRAY)
    edges = hard_edges(luma)
    if inside is not None:
        edges &= np.asarray(inside, bool).view(np.uint8)
    if not edges.any():
        return None
    H, W = edges.shape
    n, _, stats, _ = components_with_stats(cv2.dilate(edges, np.ones((3, 3), np.uint8)))
    boxes = stats[1:n, :4].astype(np.int64)
    boxes = boxes[(boxes[:, 3] >= MIN_HEIGHT_PX) & (boxes[:, 3] <= MAX_HEIGHT_FRAC * H)][:_MAX_GLYPHS]
    lines = []
    for cands in text_lines(boxes):  # the first of a chain's boxes whose rows step as text does
        for x, y, w, h in cands:
            if (strokes_per_height(luma[y:y + h, x:x + w]) >= MIN_STROKES_PER_HEIGHT
                    and edges[y:y + h, x:x + w].mean() >= MIN_FILL):
                lines.append((x, y, w, h))
                break
    found = [b for b in lines if b[2] >= MIN_ASPECT * b[3]]
    found += [b for b in lines if b[2] < MIN_ASPECT * b[3] and any(_stacked(b, f) for f in found)]
    if not found:
        return None
    out = np.zeros((H, W), bool)
    reach = np.zeros((H, W), bool)
    for x, y, w, h in found:
        g = max(2, (h + 3) // 4)  # the outline's and the strokes' blur: a quarter of the line's height
        out[max(y - g, 0): y + h + g, max(x - g, 0): x + w + g] = True
        g = h  # a banner's black margin (its descent and padding), up to a height beyond
        reach[max(y - g, 0): y + h + g, max(x - g, 0): x + w + g] = True
    dark = cv2.dilate((luma <= BLACK_DN).view(np.uint8), np.ones((3, 3), np.uint8)) > 0
    return out | (reach & dark)


def text_lines(boxes: np.ndarray) -> list[list[tuple[int, int, int, int]]]:
    """Glyph boxes (N, 4) (x, y, w, h) chained into lines: two glyphs are of one line when their
    heights differ by less than 2× and they share half the smaller's rows (or the smaller, up
    to 4× smaller, lies within the taller's rows: punctuation, and the pieces a drop shadow
    breaks a glyph into at the working size), and the gap between them is at most
    ``_GLYPH_GAP`` of the taller one's height. Returns per chain its candidate boxes
    (x, y, w, h): the union of its glyphs, and its core (the rows of the width-weighted median
    top and bottom of its glyphs, where a skyline's edge touches the line; the glyphs centred
    there), each at least ``MIN_ASPECT`` / 2 as wide as tall (a name over a clock may be short;
    :func:`overlay_text` decides)."""
    if not len(boxes):
        return []
    x, y, w, h = (boxes[:, k][:, None] for k in range(4))
    xt, yt, wt, ht = (boxes[:, k][None, :] for k in range(4))
    hmax, hmin = np.maximum(h, ht), np.minimum(h, ht)
    overlap = np.minimum(y + h, yt + ht) - np.maximum(y, yt)
    gap = np.maximum(x, xt) - np.minimum(x + w, xt + wt)
    alike = (hmax < 2 * hmin) & (overlap >= 0.5 * hmin)  # two glyphs
    within = (hmax < 4 * hmin) & (overlap >= 0.9 * hmin)  # a colon, a dot, a fragment of a shadowed glyph
    linked = (alike | within) & (gap <= _GLYPH_GAP * hmax)
    label = _chains(linked)
    out = []
    for k in np.unique(label):
        b = boxes[label == k]
        union = _box(b)
        # the core: the rows of the width-weighted median top and bottom of its glyphs (a
        # skyline's edge that touches the line is not one of them), the glyphs centred there
        y0 = int(weighted_median(b[:, 1], b[:, 2]))
        y1 = int(weighted_median(b[:, 1] + b[:, 3], b[:, 2]))
        c2 = 2 * b[:, 1] + b[:, 3]
        core = b[(c2 >= 2 * y0) & (c2 <= 2 * y1)]
        cands = [union] + ([_box(core)] if len(core) and _box(core) != union else [])
        cands = [c for c in cands if c[2] >= 0.5 * MIN_ASPECT * c[3]]
        if cands:
            out.append(cands)
    return out


def _chains(linked: np.ndarray) -> np.ndarray:
    """The connected components of a symmetric (N, N) bool adjacency: each node's label, (N,) int."""
    parent = np.arange(len(linked))

    def root(i: int) -> int:
        while parent[i] != i:
            parent[i] = parent[parent[i]]
            i = parent[i]
        return i

    for i, j in zip(*np.nonzero(np.triu(linked, 1))):
        ri, rj = root(int(i)), root(int(j))
        if ri != rj:
            parent[max(ri, rj)] = min(ri, rj)
    return np.array([root(i) for i in range(len(linked))])


def _box(b: np.ndarray) -> tuple[int, int, int, int]:
    x0, y0 = int(b[:, 0].min()), int(b[:, 1].min())
    return x0, y0, int((b[:, 0] + b[:, 2]).max()) - x0, int((b[:, 1] + b[:, 3]).max()) - y0


def _stacked(b, line) -> bool:
    """Whether box ``b`` sits right above or below the text line ``line`` (a line's height apart
    at most) and shares columns with it: the camera's name over its clock."""
    x, y, w, h = b
    lx, ly, lw, lh = line
    vgap = max(ly - (y + h), y - (ly + lh))
    return vgap <= 1.2 * max(h, lh) and min(x + w, lx + lw) > max(x, lx)
