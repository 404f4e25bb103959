"""Cloud segmentation (``hybrid``, the default) on a torch device: the per-pixel work of
:func:`cbh.pipeline.segment.segment` on tensors, its statistics on the host.

The split follows where the work is:

- per pixel, on the device (every pixel of the working image, ≈ 10⁶): NBR, chroma and
  brightness, the clear-sky references interpolated between their regions, the blue deficit,
  the desaturation and brightness cues, the score and its threshold, local contrast;
- on the host, from a regular subsample (≈ 25 000 pixels, :func:`~.segment.sample_lattice`,
  brought back once per reference): each region's percentile and the smooth surface through
  them (:func:`~.segment.reference_tables`), Li's threshold and the class medians
  (:func:`~.segment.hybrid_classes`, :func:`~.segment.one_class_is_clear`). These are sorts and
  6-parameter least squares on a few thousand values: shared code, not ported, so both
  backends take the same decisions from the same samples.

What stays on the OpenCV path: the other methods (``nbr``, ``nbr_adaptive``, ``otsu``: one
threshold, nothing for a device to gain), images without geometry (``cbh segment`` on a bare
photograph: its regions come from the image's disk and saturated sun, found by connected
components), images above ``max_side_px`` (area-averaged on the host first) and thumbnails
under 16 px a side.

Parity with the OpenCV path (tests/test_torch_parity.py): the references differ by float32
rounding and by cv2.remap's 1/32-pixel bilinear weights (≤ 1e-3 in NBR), so the masks agree
except on pixels whose score is within that of the threshold (≥ 99.5 % of pixels).
"""
from __future__ import annotations

import math

import cv2
import numpy as np
import torch
import torch.nn.functional as F

from cbh.pipeline.config import SegmentationConfig
from cbh.pipeline.segment import (
    _PSI_EDGES_DEG, _REF_STRIDE, _Z_EDGES_DEG, BRIGHTNESS_MIN_CLEAR, PROFILE_STEPS_PER_DEG, _LazyTexture, aureole_profile, check_colour, hybrid_classes,
    clear_class_is_sky, faint_cloud_on_blue, horizon_whitening, one_class_is_clear, profile_table, reference_tables, sample_lattice, segment,
)
from cbh.pipeline.torch_ops import box, upload

__all__ = ["segment_torch"]

_MIN_SIDE_PX = 16  # smaller images go to the host (the box filters' reflect padding needs a few pixels)


def _frac_index(x: torch.Tensor, edges: np.ndarray) -> torch.Tensor:
    """Fractional bin index of ``x`` between the bins' centres (``np.interp`` onto 0 … n − 1,
    clamped at both ends)."""
    c = 0.5 * (edges[:-1] + edges[1:])
    if len(c) == 1:
        return torch.zeros_like(x)
    ct = torch.as_tensor(c, dtype=x.dtype, device=x.device)
    i = (torch.searchsorted(ct, x.contiguous(), right=True) - 1).clamp(0, len(c) - 2)
    f = i.to(x.dtype) + (x - ct[i]) / (ct[i + 1] - ct[i])
    return f.clamp(0.0, float(len(c) - 1))


def _lookup(table: np.ndarray, fu: torch.Tensor, fv: torch.Tensor) -> torch.Tensor:
    """Bilinear value of ``table`` (nu, nv) at fractional indices (fu, fv) (inside the table)."""
    t = upload(table, fu.device, torch.float32)
    nu, nv = t.shape
    u0 = fu.floor().long().clamp(0, nu - 1)
    v0 = fv.floor().long().clamp(0, nv - 1)
    u1, v1 = (u0 + 1).clamp(max=nu - 1), (v0 + 1).clamp(max=nv - 1)
    wu, wv = fu - u0, fv - v0
    top = t[u0, v0] * (1 - wv) + t[u0, v1] * wv
    bottom = t[u1, v0] * (1 - wv) + t[u1, v1] * wv
    return top * (1 - wu) + bottom * wu


def _references(features, usable: torch.Tensor, zenith: torch.Tensor, sun: torch.Tensor | None, q: float):
    """:func:`~.segment.clear_sky_references` with geometry, on the device (the tables on the host)."""
    H, W = usable.shape
    ue = np.asarray(_Z_EDGES_DEG, np.float32)
    ve = np.asarray(_PSI_EDGES_DEG, np.float32) if sun is not None else None
    sl = sample_lattice(int(usable.count_nonzero()))
    m = usable[sl]
    host = lambda a: a[sl][m].cpu().numpy()  # noqa: E731
    tables = reference_tables([host(f) for f in features], host(zenith), ue, host(sun) if sun is not None else None,
                              ve, q)
    c = (slice(0, None, _REF_STRIDE), slice(0, None, _REF_STRIDE))  # on a coarser grid, then resized (as the host)
    fu = _frac_index(zenith[c], ue)
    fv = _frac_index(sun[c], ve) if sun is not None else torch.zeros_like(fu)
    out = []
    for ref in tables:
        if ref is None:
            out.append(torch.zeros((H, W), dtype=torch.float32, device=usable.device))
            continue
        small = _lookup(ref if sun is not None else ref[:, :1], fu, fv)
        out.append(F.interpolate(small[None, None], size=(H, W), mode="bilinear", align_corners=False)[0, 0])
    return out


def _local_contrast(grey: torch.Tensor, window_px: int = 7) -> torch.Tensor:
    """:func:`~.segment.local_contrast` of a grey image (H, W) float32 (BORDER_REFLECT_101 box)."""
    g = grey[None, None]
    m = box(g, window_px)
    var = (box(g * g, window_px) - m * m).clamp_min(0.0)
    return (var.sqrt() / m.clamp_min(1.0))[0, 0]


def _minus_aureole(feature: torch.Tensor, feature_s: np.ndarray, sun_s: np.ndarray, sun: torch.Tensor,
                   q: float, texture_s: np.ndarray | None = None) -> torch.Tensor:
    """:func:`~.segment._minus_aureole` on the device: the profile from host samples, then the
    same quarter-degree table lookup as :func:`~.segment.apply_profile`."""
    prof = aureole_profile(feature_s, sun_s, q, texture_s)
    if prof is None:
        return feature
    table = torch.as_tensor(profile_table(prof), device=sun.device)
    idx = torch.round(sun * PROFILE_STEPS_PER_DEG).clamp(0, 255).long()  # as segment.apply_profile
    return feature - table[idx]


def segment_torch(image_bgr: np.ndarray, usable: np.ndarray, zenith_deg, sun_angle_deg, cfg: SegmentationConfig,
                  device: torch.device | str = "cpu", what: str = "image",
                  sky_clear: bool = False) -> tuple[np.ndarray, float]:
    """:func:`cbh.pipeline.segment.segment` with its per-pixel work on ``device``.

    Parameters and result as :func:`~.segment.segment`; ``zenith_deg`` and ``sun_angle_deg``
    may be numpy arrays or tensors (already on the device: not uploaded again). Methods other
    than ``hybrid``, images without geometry (``zenith_deg`` None) and images above
    ``max_side_px`` run :func:`~.segment.segment` itself (see the module docstring).
    """
    check_colour(image_bgr, what)
    H, W = image_bgr.shape[:2]
    if (cfg.method.lower() != "hybrid" or zenith_deg is None or min(H, W) < _MIN_SIDE_PX
            or (cfg.max_side_px and max(H, W) > cfg.max_side_px)):
        host = lambda a: a.cpu().numpy() if isinstance(a, torch.Tensor) else a  # noqa: E731
        return segment(image_bgr, usable, host(zenith_deg), host(sun_angle_deg), cfg, what, sky_clear)
    dev = torch.device(device)
    img = upload(image_bgr, dev)
    b, g, r = (img[..., k].float() for k in range(3))
    mx = torch.maximum(torch.maximum(b, g), r)
    mn = torch.minimum(torch.minimum(b, g), r)
    nbr = (b - r) / (b + r).clamp_min(1.0)
    chroma = (mx - mn) / mx.clamp_min(1.0)
    use = upload(usable, dev) & (mx >= cfg.min_brightness)
    n_use = int(use.count_nonzero())
    if n_use == 0:
        return np.zeros((H, W), bool), 0.0
    zen = upload(zenith_deg, dev, torch.float32)
    sun = upload(sun_angle_deg, dev, torch.float32) if sun_angle_deg is not None else None
    ref_n, ref_s = _references([nbr, chroma], use, zen, sun, cfg.clear_percentile)
    r_n = ref_n - nbr  # blue deficit against the clear sky of the same region
    r_s = (ref_s - chroma) / ref_s.clamp_min(0.02)  # relative desaturation
    sub = sample_lattice(n_use)
    us = use[sub]
    if sun is not None:  # the aureole is clear sky: its own excess removed (see segment._hybrid)
        psi_s = sun[sub][us].cpu().numpy()
        q = 100.0 - cfg.clear_percentile
        us_h = us.cpu().numpy()
        tex = _LazyTexture(image_bgr)  # host: OpenCV's blur, as segment._hybrid
        tex_s = lambda: tex()[sub][us_h]  # noqa: E731
        r_n = _minus_aureole(r_n, r_n[sub][us].cpu().numpy(), psi_s, sun, q, tex_s)
        r_s = _minus_aureole(r_s, r_s[sub][us].cpu().numpy(), psi_s, sun, q, tex_s)
    rs = r_n[sub][us].cpu().numpy()
    if rs.size == 0:  # no usable pixel on the sampling lattice (as segment._hybrid: nothing classified)
        return np.zeros((H, W), bool), 0.0
    gap = hybrid_classes(rs, chroma[sub][us].cpu().numpy(), cfg)
    # OpenCV's grey conversion, uploaded (its SIMD rounding differs from any one formula by a grey
    # level on 0.1 % of pixels); only where the texture decides
    grey = lambda: upload(cv2.cvtColor(image_bgr, cv2.COLOR_BGR2GRAY), dev, torch.float32)  # noqa: E731
    if gap is None:  # one class only: the whole usable sky is clear or cloud
        contrast = lambda: _local_contrast(grey())[sub][us].cpu().numpy()  # noqa: E731
        nbr_s = nbr[sub][us].cpu().numpy()
        white = None if sun is None or zen is None else horizon_whitening(
            nbr_s, zen[sub][us].cpu().numpy(), sun[sub][us].cpu().numpy())
        if not sky_clear and not faint_cloud_on_blue(rs, nbr_s, cfg) and not one_class_is_clear(
                nbr_s, contrast, cfg, chroma[sub][us].cpu().numpy(), white):
            return use.cpu().numpy(), 1.0  # overcast
        score = r_n / (cfg.min_gap * 2.0)
    else:
        score = r_n / gap
    score = score * (1.0 - cfg.chroma_weight) + r_s * cfg.chroma_weight
    cloud = (score > cfg.score_threshold) & use
    if gap is not None and cfg.brightness_weight > 0:
        # the brightness cue (see segment._hybrid): brightness against the clear sky found so far
        clear = use & ~cloud
        if int(clear.count_nonzero()) >= BRIGHTNESS_MIN_CLEAR * n_use:
            v_ref = _references([mx / 255.0], clear, zen, sun, 50.0)[0]
            dv = torch.log(mx.clamp_min(1.0)) - torch.log((v_ref * 255.0).clamp_min(1.0))
            if sun is not None:
                cs_ = clear[sub]
                cs_h = cs_.cpu().numpy()
                dv = _minus_aureole(dv, dv[sub][cs_].cpu().numpy(), sun[sub][cs_].cpu().numpy(), sun, 50.0,
                                    lambda: tex()[sub][cs_h])
            dv = dv.abs()
            score = score + dv * (cfg.brightness_weight / math.log(1.5))
            cloud = (score > cfg.score_threshold) & use
    if gap is not None and not sky_clear:  # (as segment._hybrid) a clear class that no clear sky could be: all cloud
        clear_s = (use & ~cloud)[sub]
        if not clear_class_is_sky(nbr[sub][clear_s].cpu().numpy(),
                                  lambda: _local_contrast(grey())[sub][clear_s].cpu().numpy(), cfg):
            return use.cpu().numpy(), 1.0
    return cloud.cpu().numpy(), float(cloud.count_nonzero()) / n_use
