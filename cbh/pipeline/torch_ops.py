"""Torch backend (any device: ``"cpu"``, ``"cuda"``, ``"cuda:1"`` …) for the dense per-pair work.

What runs here, on tensors that stay on the device until the per-pair result is read back:

- the plane sweep (:func:`sweep_field_torch`; :func:`sweep_matches_torch` as points): the same
  four passes as :mod:`.sweep`, with the same two-tier coarse planes
  (coarse → fine → label → refine), with the ZNCC of *all* planes of a pass in one batched
  call (chunked on CPU to bound memory) instead of a loop over planes; the 1-D steps (vote
  histograms, peaks, plane selection, far-layer box) are shared with :mod:`.sweep` unchanged;
- the sun angle map of the masks stage (:func:`angle_map_deg_torch`);
- segmentation's per-pixel work (:mod:`.torch_segment`; its statistics on a subsample stay on
  the host, in code shared with the OpenCV path);
- the height map's hole fill (:mod:`.torch_heightmap`): every pixel's nearest measured pixel,
  by jump flooding, since kornia's ``distance_transform`` gives distances without the nearest
  pixel's label (OpenCV's ``distanceTransformWithLabels``).

kornia where it fits:

- remapping: ``kornia.geometry.transform.remap`` with ``align_corners=True`` is cv2.remap's
  pixel-centre convention (pixel x = 0 is the centre of the first column: kornia normalises
  by 2/(W − 1), which only ``align_corners=True`` maps back to pixel centres; its default,
  False, is off by up to half a pixel at the edges). :func:`remap` wraps it; the sweep itself
  samples with ``torch.nn.functional.grid_sample`` on plane grids *pre-normalised* the same
  way (the cubic p2(s) = m0 + a·s + b·s² + c·s³ is linear in the tables, so normalising the four
  tables once equals normalising every plane's map), which saves kornia's per-call stack and
  normalisation of a (P, h, w, 2) grid;
- box filters: not ``kornia.filters.box_blur``: for even sizes it anchors the box on the
  other side of the pixel than cv2.boxFilter (the sweep's block-aligned windows need
  OpenCV's anchor), so :func:`box` is a reflect pad (= BORDER_REFLECT_101, the border the
  OpenCV path uses) and two 1-D average pools (separable);
- 2 × 2 pooling and block means: ``avg_pool2d`` (OpenCV's exact INTER_AREA for integer factors).

What stays on OpenCV, and why:

- the sparse matchers (LK, ORB, DIS): feature detection and pyramidal tracking of a few
  thousand points; no kornia equivalent with forward-backward checks, and little to gain;
- the saturation mask: connected components *with areas* (``connectedComponentsWithStats``);
  ``kornia.contrib.connected_components`` is an iterative label propagation without areas;
- the working-size resize and grey conversion (uint8 in, uint8 out, as the sparse matchers
  need them; 2 ms);
- segmentation's statistics (per-region percentiles, Li's threshold and a robust surface fit on
  ≈ 25 000 sampled pixels: sorts and small least squares, nothing for a GPU to gain): the
  samples are brought back once per reference (:mod:`.torch_segment`); on the OpenCV backend
  the whole of segmentation stays there (≈ 30 ms per camera at 960 px on one core, against
  40–100 ms for the torch code on one CPU thread);
- the height map's assembly from the sweep's field (closed form, a few OpenCV operations on the
  field as the sweep hands it back) and the layer statistics (histograms of ≈ 10⁴ points).

Precision: float32 throughout, as the OpenCV path; ZNCC values agree with it to ≈ 1e-5
(different summation order of the box filters), see tests/test_torch_parity.py.
"""
from __future__ import annotations


import numpy as np
import torch
import torch.nn.functional as F
from kornia.geometry.transform import remap as _kornia_remap

from cbh.pipeline.sweep import (
    _GROWN_APART_PX, CoarseLayers, FineCost, LayerLabels, PassTimer, PlaneMaps, _bbox, plane_lattice, plane_range, coarse_planes,
    coarse_regions, coarse_layers, fine_planes, layer_box, layer_interior, layer_planes, own_plane_peaks, parallax_reach,
    peak_offset, reach_levels,
    resolved_layers, truncated, vote_layers, SweepField, field_points,
)

__all__ = ["upload", "remap", "box", "pool2", "TorchPlaneMaps", "zncc_half", "sweep_matches_torch", "sweep_field_torch", "angle_map_deg_torch",
           "resolve_device"]

_CPU_CHUNK_PX = 4_000_000  # CPU: planes per batched call × pixels per plane at most (bounds temporaries)


def resolve_device(device: str | torch.device) -> torch.device:
    """A torch device from a user string; a clear error for CUDA on a machine without it."""
    from cbh.errors import ConfigError

    try:
        dev = torch.device(device)
    except (RuntimeError, TypeError) as e:
        raise ConfigError(f"device: {device!r} is not a torch device ({e})") from None
    if dev.type == "cuda" and not torch.cuda.is_available():
        raise ConfigError(f"device {device!r}: CUDA is not available on this machine (use --device cpu)")
    return dev


def remap(image: torch.Tensor, map_x: torch.Tensor, map_y: torch.Tensor) -> torch.Tensor:
    """cv2.remap (INTER_LINEAR, BORDER_CONSTANT 0) on tensors.

    Parameters
    ----------
    image : tensor, shape (B, C, H, W), float
    map_x, map_y : tensor, shape (B, h, w), float
        Source pixel coordinates (pixel centres at integers, as OpenCV).

    Returns
    -------
    tensor, shape (B, C, h, w)
    """
    return _kornia_remap(image, map_x, map_y, mode="bilinear", padding_mode="zeros", align_corners=True)


def box(x: torch.Tensor, k: int) -> torch.Tensor:
    """cv2.boxFilter (normalised, BORDER_REFLECT_101) of (B, C, H, W): the mean over pixels
    x − k//2 … x + k − 1 − k//2 (OpenCV's anchor; for even k kornia's ``box_blur`` takes the
    other side, so it serves odd k only: both are done here as a reflect pad and an average pool)."""
    k = int(k)
    if k <= 1:
        return x
    lo, hi = k // 2, k - 1 - k // 2
    x = F.avg_pool2d(F.pad(x, (0, 0, lo, hi), mode="reflect"), (k, 1), stride=1)  # separable: 2k, not k², adds
    return F.avg_pool2d(F.pad(x, (lo, hi, 0, 0), mode="reflect"), (1, k), stride=1)


def pool2(x: torch.Tensor) -> torch.Tensor:
    """Mean of each 2 × 2 block, (B, C, H, W) → (B, C, H // 2, W // 2)."""
    return F.avg_pool2d(x, 2)


def upload(a, device, dtype: torch.dtype | None = None) -> torch.Tensor:
    """A numpy array (or a tensor) as a tensor on ``device``. Read-only arrays (the table cache's,
    memory-mapped) are copied first: torch cannot share memory it must treat as writable."""
    if isinstance(a, torch.Tensor):
        return a.to(device=device, dtype=dtype or a.dtype)
    a = np.ascontiguousarray(a)
    if not a.flags.writeable:
        a = a.copy()
    t = torch.as_tensor(a, device=device)
    return t if dtype is None else t.to(dtype)


class TorchPlaneMaps:
    """:class:`~cbh.pipeline.sweep.PlaneMaps` on a device (uploaded once per camera pair).

    ``grid(s, region)`` is the (P, h, w, 2) sampling grid of planes s (P,) in grid_sample's
    normalised coordinates (align_corners=True); ``points`` evaluates camera-2 pixels.
    """

    def __init__(self, maps: PlaneMaps, size2: tuple[int, int], device: torch.device):
        w2, h2 = size2
        self.device, self.s_a, self.scale_px, self.size2 = device, maps.s_a, maps.scale_px, size2
        self.maps = maps
        scale = torch.tensor([2.0 / max(w2 - 1, 1), 2.0 / max(h2 - 1, 1)], device=device)
        m0 = upload(maps.m0, device, torch.float32)
        outside = m0[..., 0] < -1.0e3
        self.m0n = m0 * scale - 1.0
        self.m0n[outside] = -10.0  # far outside [-1, 1]: zeros padding
        self.an = upload(maps.a, device, torch.float32) * scale
        self.bn = upload(maps.b, device, torch.float32) * scale
        self.m0, self.a, self.b = m0, upload(maps.a, device, torch.float32), upload(maps.b, device, torch.float32)
        self.c = None if maps.c is None else upload(maps.c, device, torch.float32)
        self.cn = None if maps.c is None else self.c * scale
        self._down: dict[int, TorchPlaneMaps] = {}

    def downsampled(self, factor: int, size2: tuple[int, int]) -> "TorchPlaneMaps":
        if factor not in self._down:
            self._down[factor] = TorchPlaneMaps(self.maps.downsampled(factor), size2, self.device)
        return self._down[factor]

    def grid(self, s: torch.Tensor, region) -> torch.Tensor:
        s = s.reshape(-1, 1, 1, 1)
        if self.cn is None:
            return self.m0n[region] + s * (self.an[region] + s * self.bn[region])
        return self.m0n[region] + s * (self.an[region] + s * (self.bn[region] + s * self.cn[region]))

    def points(self, s: torch.Tensor, yi: torch.Tensor, xi: torch.Tensor) -> torch.Tensor:
        """Camera-2 pixels (N, 2) at per-pixel s (N,) for camera-1 pixels (yi, xi) (float32)."""
        s = s[:, None]
        if self.c is None:
            return self.m0[yi, xi] + (self.a[yi, xi] + self.b[yi, xi] * s) * s
        return self.m0[yi, xi] + (self.a[yi, xi] + (self.b[yi, xi] + self.c[yi, xi] * s) * s) * s


def zncc_half(i1: torch.Tensor, g2: torch.Tensor, tm: TorchPlaneMaps, s: np.ndarray, half_window: int,
              region) -> tuple[torch.Tensor, torch.Tensor]:
    """ZNCC at half resolution over 2·half_window block-aligned windows (see
    :func:`cbh.pipeline.sweep._zncc_half_iter`), all planes batched.

    Parameters
    ----------
    i1 : tensor, shape (h, w), float32 — image 1 on the region (h, w even)
    g2 : tensor, shape (H2, W2), float32 — image 2
    tm : TorchPlaneMaps
    s : ndarray, shape (P,) [1/m]
    half_window : int
    region : (slice, slice) of camera 1's grid

    Returns
    -------
    std1 : tensor (h/2, w/2); scores : tensor (P, h/2, w/2), float32
    """
    k = int(half_window)
    dev = i1.device
    off = 1 - k % 2  # even k: blocks one pixel in (see the OpenCV twin)
    if off:
        i1 = i1[1:-1, 1:-1]
        region = (slice(region[0].start + 1, region[0].stop - 1), slice(region[1].start + 1, region[1].stop - 1))
    x1 = i1[None, None]
    p1 = pool2(torch.cat([x1, x1 * x1], 1))
    b1 = box(p1, k)
    mu1, var1 = b1[:, :1], (b1[:, 1:] - b1[:, :1] ** 2).clamp_min(0.0)
    h, w = i1.shape
    s_t = torch.as_tensor(np.asarray(s, np.float32), device=dev)
    n = len(s_t)
    chunk = n if dev.type != "cpu" else max(1, _CPU_CHUNK_PX // max(h * w, 1))
    out = torch.empty((n, h // 2, w // 2), dtype=torch.float32, device=dev)  # (one less each way if off)
    src = g2[None, None]
    for c0 in range(0, n, chunk):
        sc = s_t[c0: c0 + chunk]
        grid = tm.grid(sc, region)
        wv = F.grid_sample(src.expand(len(sc), 1, -1, -1), grid, mode="bilinear", padding_mode="zeros",
                           align_corners=True)
        b = box(pool2(torch.cat([wv, wv * wv, x1 * wv], 1)), k)
        mu2 = b[:, :1]
        var2 = (b[:, 1:2] - mu2 * mu2).clamp_min(0.0)
        cov = b[:, 2:3] - mu1 * mu2
        # clamped: beyond ±1 is the box sums' float32 rounding in a flat window (see the OpenCV twin)
        out[c0: c0 + len(sc)] = (cov / torch.sqrt(var1 * var2 + 1e-3)).clamp(-1.0, 1.0)[:, 0]
    std1 = torch.sqrt(var1[0, 0])
    if off:  # the last row and column repeat their neighbours
        std1 = F.pad(std1[None, None], (0, 1, 0, 1), mode="replicate")[0, 0]
        out = F.pad(out[:, None], (0, 1, 0, 1), mode="replicate")[:, 0]
    return std1, out


def _best3(stack: torch.Tensor):
    """Index of the best plane (first of equal maxima), its score and its neighbours' scores."""
    j = stack.argmax(0, keepdim=True)
    n = stack.shape[0]
    c = stack.gather(0, j)
    left = stack.gather(0, (j - 1).clamp_min(0))
    right = stack.gather(0, (j + 1).clamp_max(n - 1))
    return j[0], c[0], left[0], right[0]


def _refine(j, c0, cm1, cp1, s_values: np.ndarray, ds: float) -> torch.Tensor:
    """The score's peak from planes j−1, j, j+1 (where adjacent), as :func:`cbh.pipeline.sweep._refine`."""
    dev = c0.device
    n = len(s_values)
    sv = torch.as_tensor(np.asarray(s_values, np.float32), device=dev)
    gap = torch.as_tensor(np.diff(s_values, prepend=-np.inf, append=np.inf), device=dev)
    adj = (j > 0) & (j < n - 1) & (gap[j] < 1.01 * ds) & (gap[(j + 1).clamp_max(n)] < 1.01 * ds)
    delta = torch.where(adj, peak_offset(c0, cm1, cp1, xp=torch), torch.zeros_like(c0))
    return sv[j] + delta * float(ds)


def _oblique_peaks(prod: torch.Tensor, label: torch.Tensor, sel: np.ndarray, s: np.ndarray, ds: float, kL: int,
                   levels: list, reach: torch.Tensor | None):
    """As :func:`cbh.pipeline.sweep._oblique_peaks` on the layer's masked costs ``prod`` (n, h, w)."""
    h, w = prod.shape[1:]
    ja, s_half = _peak_of(box(prod[None], kL)[0], s[sel], ds)
    for f, split in levels:
        here = label & (reach < split)
        if not bool(here.any()):
            break
        prod = pool2(prod[None])[0]
        jg, sg = _peak_of(box(prod[None], kL)[0], s[sel], ds)
        pad = (0, w - jg.shape[1] * f, 0, h - jg.shape[0] * f)
        cut = torch.as_tensor(truncated(np.asarray(sel)[jg.cpu().numpy()], s, ds), device=prod.device)
        cut = F.pad(cut.repeat_interleave(f, 0).repeat_interleave(f, 1)[None, None].float(), pad, mode="replicate")
        jb = F.pad(jg.repeat_interleave(f, 0).repeat_interleave(f, 1)[None, None].float(), pad, mode="replicate")
        near = (jb[0, 0] - ja.float()).abs() * reach <= _GROWN_APART_PX
        sg = F.pad(F.interpolate(sg[None, None], scale_factor=f, mode="bilinear", align_corners=False), pad, mode="replicate")
        s_half = torch.where(here & (cut[0, 0] == 0) & near, sg[0, 0], s_half)
    return ja, s_half


def _peak_of(agg: torch.Tensor, s_sel: np.ndarray, ds: float):
    ja, ca, la, ra = _best3(agg)
    return ja, _refine(ja, ca, la, ra, s_sel, ds)


def _region_t(r):
    return (slice(r[0].start, r[0].stop), slice(r[1].start, r[1].stop))


def coarse_pass_torch(g1: torch.Tensor, g2: torch.Tensor, cloud1: np.ndarray, tm: TorchPlaneMaps, s_min: float,
                      s_max: float, o1z: float, cfg) -> CoarseLayers | None:
    """Pass 1 on the device (see :func:`cbh.pipeline.sweep.coarse_pass`; the same planes,
    regions and votes: :func:`~cbh.pipeline.sweep.coarse_planes`, ``coarse_regions``,
    :func:`~cbh.pipeline.sweep.coarse_votes`)."""
    f = max(int(cfg.coarse_factor), 1)
    plan = coarse_planes(s_min, s_max, tm.scale_px, cfg)
    reg = coarse_regions(cloud1, plan, cfg)
    if reg is None:
        return None
    cl, slc, half = reg
    c1 = F.avg_pool2d(g1[None, None], f)[0, 0] if f > 1 else g1
    c2 = F.avg_pool2d(g2[None, None], f)[0, 0] if f > 1 else g2
    k = cfg.coarse_window_px // 2

    def best(a1, a2, factor, s, region):
        cm = tm.downsampled(factor, (a2.shape[1], a2.shape[0])) if factor > 1 else tm
        _, sc = zncc_half(a1[region].contiguous(), a2, cm, s, k, region)
        c, j = sc.max(0)
        return j.cpu().numpy(), c.cpu().numpy()

    j_far = c_far = j_near = c_near = None
    if len(plan.far):
        j_far, c_far = best(c1, c2, f, plan.s[plan.far], slc)
    if half is not None:
        j_near, c_near = best(pool2(c1[None, None])[0, 0], pool2(c2[None, None])[0, 0], 2 * f, plan.s[plan.near], half)
    return coarse_layers(plan, cl, j_far, c_far, j_near, c_near, o1z, cfg)


def fine_pass_torch(g1: torch.Tensor, g2: torch.Tensor, cloud1: np.ndarray, tm: TorchPlaneMaps, s: np.ndarray,
                    ds: float, cfg) -> FineCost:
    """Pass 2 on the device (see :func:`cbh.pipeline.sweep.fine_pass`); arrays of the result are tensors."""
    sl = _bbox(cloud1, cfg.window_px, even=True)
    i1 = g1[sl].contiguous()
    h, w = i1.shape
    k = int(cfg.window_px)
    b = box(torch.stack([i1, i1 * i1])[None], k)[0]
    var = (b[1] - b[0] ** 2).clamp_min(0.0)
    cl = torch.as_tensor(np.ascontiguousarray(cloud1[sl]), device=g1.device)
    m0 = cl & (var >= float(cfg.min_texture) ** 2)
    textured = pool2(m0.float()[None, None])[0, 0]
    _, sc = zncc_half(i1, g2, tm, s, k // 2, sl)
    best = sc.max(0).values
    up = best.repeat_interleave(2, 0).repeat_interleave(2, 1)
    ok = m0 & (up >= cfg.min_zncc)
    return FineCost(sl, s, ds, sc * textured, textured, ok, pool2(ok.float()[None, None])[0, 0],
                    plane_lattice(tm.scale_px, cfg),
                    upload(parallax_reach(tm.maps, sl), g1.device) if cfg.oblique_levels > 0 else None)


def label_pass_torch(fine: FineCost, cfg) -> LayerLabels:
    """Pass 3 on the device (see :func:`cbh.pipeline.sweep.label_pass`)."""
    s, ds, cost = fine.u, fine.ds, fine.cost  # (the planes' lattice coordinate: evenly spaced)
    dev = cost.device
    k2 = max(3, (int(cfg.aggregate_px) // 2) | 1)
    kl = max(1, (int(cfg.label_px) // 2) | 1)
    jw, cw, lw, rw = _best3(box(cost[None], k2)[0])
    s_w = _refine(jw, cw, lw, rw, s, ds)
    vote = fine.ok_frac > 0
    if cfg.vote_percentile > 0 and bool(vote.any()):
        mean_w = cw / box(fine.textured[None, None], k2)[0, 0].clamp_min(1e-6)
        vote &= mean_w >= torch.quantile(mean_w[vote].double(), cfg.vote_percentile / 100.0).float()
    own = cost.argmax(0)

    def regional(peaks):
        return own_plane_peaks(own.cpu().numpy(), fine.ok_frac.cpu().numpy(), s, ds, cfg, peaks)

    votes, bw, ranges, cuts, plane_layer = vote_layers(s_w[vote].cpu().numpy(), fine.ok_frac[vote].cpu().numpy(),
                                                       s, ds, float(fine.ok_frac.sum().item()), cfg, regional)
    hh, wh = cost.shape[1:]
    label = torch.zeros((hh, wh), dtype=torch.uint8, device=dev)
    if len(ranges) > 1:
        b = box(cost[None], kl)[0] if kl > 1 else cost
        per_layer = torch.full((len(ranges), hh, wh), -torch.inf, device=dev)
        for L in range(len(ranges)):
            q = np.flatnonzero(plane_layer == L)
            if len(q):
                per_layer[L] = b[torch.as_tensor(q, device=dev)].max(0).values
        label = per_layer.argmax(0).to(torch.uint8)
    return LayerLabels(cuts, votes, bw, ranges, plane_layer, label, own, s_w)


def refine_pass_torch(fine: FineCost, lab: LayerLabels, scale_px: float, cfg) -> torch.Tensor:
    """Pass 4 on the device (see :func:`cbh.pipeline.sweep.refine_pass`); (h, w) float32 tensor."""
    s, ds, cost = fine.u, fine.ds, fine.cost  # (the planes' lattice coordinate: evenly spaced)
    dev = cost.device
    h, w = fine.ok.shape
    n_layers = max(len(lab.vote_ranges), 1)
    lab_full = lab.label.repeat_interleave(2, 0).repeat_interleave(2, 1)
    plane_layer = torch.as_tensor(lab.plane_layer, device=dev)
    s_px = torch.zeros((h, w), dtype=torch.float32, device=dev)
    for L in range(n_layers):
        here = fine.ok & (lab_full == L)
        if not bool(here.any()):
            continue
        sel = layer_planes(lab, L, s, ds)
        kL = layer_box(lab, L, scale_px, cfg, fine.lattice)
        k2 = max(3, (int(cfg.aggregate_px) // 2) | 1)
        levels = reach_levels(kL, k2, tuple(lab.label.shape), cfg) if fine.reach is not None else []
        oblique = bool(levels) and bool((fine.reach < levels[0][1]).any())
        if len(sel) < 3 or (n_layers == 1 and kL == k2 and len(sel) == len(s) and not oblique):
            s_half = lab.s_wide  # as the OpenCV twin: the wide-box winner itself
        else:
            mL = lab.label == L
            weight = mL.float()
            if n_layers > 1:  # as the OpenCV twin: own best plane in the layer, windows across its edge weighed less
                inner = layer_interior(mL.cpu().numpy(), cfg.window_px)
                weight = (mL & (plane_layer[lab.own_plane] == L)).float() * torch.as_tensor(inner, device=dev)
            prod = cost[torch.as_tensor(sel, device=dev)] * weight
            ja, s_half = _oblique_peaks(prod, lab.label == L, sel, s, ds, kL, levels if oblique else [], fine.reach)
            cut = torch.as_tensor(truncated(np.asarray(sel)[ja.cpu().numpy()], s, ds), device=dev)
            if bool(cut.any()):  # as the OpenCV twin: not matched where the sweep stopped
                s_half = torch.where(cut, lab.s_wide, s_half)
                gone = fine.ok & (lab_full == L) & cut.repeat_interleave(2, 0).repeat_interleave(2, 1)[:h, :w]
                here = here & ~gone
                s_px = torch.where(gone, torch.full_like(s_px, float("nan")), s_px)
        up = F.interpolate(s_half[None, None], size=(h, w), mode="bilinear", align_corners=False)[0, 0]
        s_px = torch.where(here, up, s_px)
    return fine.to_s(s_px)


def sweep_field_torch(gray1: np.ndarray, gray2: np.ndarray, cloud1: np.ndarray, tm: TorchPlaneMaps, o1z: float,
                      cfg) -> SweepField | None:
    """:func:`cbh.pipeline.sweep.sweep_field` on ``tm.device`` (same parameters; the result's
    arrays are brought back as numpy). The per-pixel ``aggregate_px = 1`` variant is not
    ported: it raises ConfigError."""
    from cbh.errors import ConfigError

    lap = PassTimer()
    if cfg.aggregate_px <= 1:
        raise ConfigError("matching.sweep.aggregate_px = 1 runs on the OpenCV backend only (device cpu)")
    info = {"planes": np.zeros(0), "layers_m": [], "timing_ms": lap.timing_ms}
    if not cloud1.any() or tm.scale_px <= 0:
        return None
    dev = tm.device
    g1 = torch.as_tensor(np.ascontiguousarray(gray1), device=dev).float()
    g2 = torch.as_tensor(np.ascontiguousarray(gray2), device=dev).float()
    s_min, s_max = plane_range(o1z, cfg)
    coarse = coarse_pass_torch(g1, g2, cloud1, tm, s_min, s_max, o1z, cfg)
    if coarse is None:
        return None
    s_fine, ds = fine_planes(coarse, tm.scale_px, s_min, s_max, cfg)
    info.update(planes=s_fine, layers_m=coarse.layers_m)
    lap("coarse")
    fine = fine_pass_torch(g1, g2, cloud1, tm, s_fine, ds, cfg)
    lap("fine")
    if not bool(fine.ok.any()):
        return None
    lab = label_pass_torch(fine, cfg)
    info.update(votes=lab.votes, vote_bin_s=lab.bin_s, cuts_s=lab.cuts_s)
    lap("layers")
    s_px = refine_pass_torch(fine, lab, tm.scale_px, cfg)
    s_np = s_px.cpu().numpy()
    out = SweepField(fine.region, fine.ok.cpu().numpy() & np.isfinite(s_np), s_np, info)
    info["resolved_m"] = resolved_layers(out.ok, out.s, lab.label.cpu().numpy(), o1z, s_min)
    lap("refine")
    return out


def sweep_matches_torch(gray1: np.ndarray, gray2: np.ndarray, cloud1: np.ndarray, tm: TorchPlaneMaps, o1z: float,
                        cfg):
    """:func:`cbh.pipeline.sweep.sweep_matches` on ``tm.device`` (same parameters and results)."""
    f = sweep_field_torch(gray1, gray2, cloud1, tm, o1z, cfg)
    if f is None:
        return np.zeros((0, 2)), np.zeros((0, 2)), {"planes": np.zeros(0), "layers_m": [], "s": np.zeros(0, np.float32)}
    px1, px2, s = field_points(f, tm.maps)
    return px1, px2, {**f.info, "s": s}


def angle_map_deg_torch(rays_cam: torch.Tensor, d_cam: np.ndarray) -> torch.Tensor:
    """Angle [deg] between each pixel's ray (H, W, 3) and a direction (3,) in the camera frame, (H, W)."""
    d = torch.as_tensor(np.asarray(d_cam, np.float32), device=rays_cam.device)
    c = (rays_cam @ d).clamp(-1.0, 1.0)
    return torch.rad2deg(torch.atan2(torch.sqrt((1.0 - c * c).clamp_min(0.0)), c))

