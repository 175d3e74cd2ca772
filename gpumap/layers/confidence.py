"""The confidence layer: occupied voxels that some view *confirmed*, apart from those that are
only *consistent* with the pings (the elevation stretch).

Definitions (``thr`` the mapper's threshold, ``s`` its voxel edge, map values as
:meth:`gpumap.MinMaxMapper.raw_values` gives them, ``+inf`` unknown):

- **not known free**: a voxel whose map value is ``>= thr`` or unknown. Only these could
  have made an echo; a voxel the map calls free (value ``< thr``) could not.
- **rival** of a ping: a not-known-free voxel (after the ping's update) that could lie in the
  ping's field of view: range in ``[r_min - rho, r_max + rho)``, azimuth within the fan's
  outer beam edges, and its bounding sphere (radius ``rho``, half the cube's diagonal) reaching
  into the vertical aperture widened by :data:`APERTURE_MARGIN`. Its *centre cell* is the
  image cell (range bin, beam) of its centre, clipped to the image.
- **cells within w** of a voxel in a ping: the image cells holding ranges
  ``[r - w, r + w]`` and azimuths ``theta -+ asin(w / h)`` (``h`` the horizontal distance; every
  beam when ``h <= w``). They run along the whole elevation arc.
- a ping **confirms** a voxel when the ping observes it bright (its ping value, the footprint
  maximum, is ``>= thr``), the map calls it occupied after the ping, some cell within
  ``tube_m`` of it is ``>= thr`` (the echo: :data:`TUBE_VOXELS`, half a voxel), and every rival
  whose centre cell lies within ``tube_m + rho`` of it (any voxel holding a point of that
  echo's cells) is the voxel itself or one of its 26 neighbours (the same surface, at the
  map's resolution): no other voxel the map does not know free could have made the echo, at
  any elevation.
- a voxel is **confirmed** when it is occupied now and some ping confirmed it (the flag is
  sticky: it records that a view once resolved the voxel's elevation; a confirmed voxel that
  later views carve is free, whatever its flag). Occupied voxels that are not confirmed are
  **unconfirmed**: consistent with every ping, but no view told them apart from the other
  voxels of their elevation arcs.

Confidence only labels occupied voxels: it never changes a map value, so it never turns an
occupied voxel free (a planner may treat unconfirmed voxels as soft obstacles and confirmed
ones as hard; both stay obstacles).

The pass is judged against the map as it stands when the ping is integrated (later pings
that carve a rival do not confirm a voxel after the fact: a new view must), so unlike the
map values the layer depends on the order of the pings; :meth:`~gpumap.MinMaxMapper.integrate_batch`
applies its pings in order and gives the layer of the same sequence of ``integrate`` calls.

:func:`confirm_ping` is the plain NumPy pass (the reference, which the ``numpy`` backend runs).
On the Warp and OpenCL backends the mapper's :class:`ConfidenceLayer` runs the same pass as
kernels on the map's device after each update (:mod:`gpumap.layers.confidence_device`,
``kernels/confidence.*``), bit for bit the reference's, reading the map where it lives; the layer
comes to the host when read. The layer keeps the flags and scores view gains against them
(:mod:`gpumap.layers.viewgain`).
"""

from __future__ import annotations

import numpy as np

from gpumap.core.integrator import check_poses
from gpumap.errors import check_finite_scalar
from gpumap.reference import beam_index_lo, beam_span, voxel_ping_values
from gpumap.spec import GridSpec, SonarSpec

__all__ = ["APERTURE_MARGIN", "TUBE_VOXELS", "ConfidenceLayer", "check_candidates", "confirm_ping",
           "voxel_states"]

_F = np.float32

#: Rivals are sought beyond the nominal vertical aperture by this fraction of it (the aperture
#: is the beam's -3 dB width; a real beam still hears weaker echoes past it). 0: the mapper's
#: own sensor model. Seen on the simulated tank and circle (issue 20): with 0 the simulator's
#: echoes from just below the aperture's lower edge (its rays reach 1.5 times the half aperture)
#: make most of the false confirmations; 0.25 or more left almost nothing confirmed on either.
APERTURE_MARGIN = 0.0

#: Half-width of the cells that must hold the echo, in voxel edges: half a voxel (the
#: elevation arc through the voxel's centre, at the map's resolution).
TUBE_VOXELS = 0.5


def _box_indices(params: np.ndarray) -> np.ndarray:
    lo = params["box_lo"].astype(np.int64)
    n = params["box_n"].astype(np.int64)
    if n.prod() == 0:
        return np.zeros((0, 3), np.int64)
    g = np.meshgrid(*(np.arange(n[a]) + lo[a] for a in range(3)), indexing="ij")
    return np.stack([x.ravel() for x in g], -1)


def _prefix(a: np.ndarray) -> np.ndarray:
    """(n+1, m+1) int64 summed-area table of a 2-D array (a zero row and column first)."""
    S = np.zeros((a.shape[0] + 1, a.shape[1] + 1), np.int64)
    S[1:, 1:] = a.cumsum(0).cumsum(1)
    return S


def _rect(S: np.ndarray, b0, b1, j0, j1) -> np.ndarray:
    """Sum over rows b0..b1 and columns j0..j1 (inclusive) from a summed-area table."""
    return S[b1 + 1, j1 + 1] - S[b0, j1 + 1] - S[b1 + 1, j0] + S[b0, j0]


def confirm_ping(
    params: np.ndarray,
    image: np.ndarray,
    edges: np.ndarray,
    values: np.ndarray,
    rival_half_vfov_rad: float,
    tube_m: float,
    arcs: np.ndarray | None = None,
) -> np.ndarray:
    """Flat indices of the voxels one ping confirms (see the module docstring).

    Parameters
    ----------
    params : PING_DTYPE record of the ping (:mod:`gpumap.geometry`), per-ping fields filled.
    image : (n_bins, n_beams) float32 in [0, 1]
        The ping's image.
    edges : (n_beams + 1,) float32 tangents of the beam-cell edges.
    values : (n,) float32
        The map values after the ping's update (``+inf`` unknown), flat C order.
    rival_half_vfov_rad : float
        Elevation (radians, either side of the boresight plane) within which a voxel's bounding
        sphere makes it a rival: ``(1 + APERTURE_MARGIN)`` times half the vertical aperture.
    tube_m : float
        Half-width of the cells that must hold the echo, metres.
    arcs : (n,) uint16, optional
        Updated in place: each voxel the ping observes gets the bit of its elevation arc's
        direction in this ping (:func:`gpumap.layers.viewgain.arc_bits`, the view gain's).

    Returns
    -------
    (m,) int64 flat voxel indices, ascending.
    """
    idx = _box_indices(params)
    if idx.shape[0] == 0:
        return np.zeros(0, np.int64)
    dims = params["dims"].astype(np.int64)
    flat = (idx[:, 0] * dims[1] + idx[:, 1]) * dims[2] + idx[:, 2]
    c = params["origin"] + (idx.astype(_F) + _F(0.5)) * params["voxel"]
    v = voxel_ping_values(params, image, edges, c)  # -1 where not observed
    A = params["A"].reshape(3, 3)
    b = params["b"]
    x = A[0, 0] * c[:, 0] + A[0, 1] * c[:, 1] + A[0, 2] * c[:, 2] + b[0]
    y = A[1, 0] * c[:, 0] + A[1, 1] * c[:, 1] + A[1, 2] * c[:, 2] + b[1]
    z = A[2, 0] * c[:, 0] + A[2, 1] * c[:, 1] + A[2, 2] * c[:, 2] + b[2]
    h2 = x * x + y * y
    h = np.sqrt(h2)
    r = np.sqrt(h2 + z * z)
    rho = params["rho"]
    rmin = params["rmin"]
    pos = x > 0
    t = y / np.where(pos, x, _F(1))
    cos_hv, sin_hv = _F(np.cos(rival_half_vfov_rad)), _F(np.sin(rival_half_vfov_rad))
    vals = values[flat]
    thr = params["thr"]
    rivals = (
        pos
        & (r >= rmin - rho)
        & (r < params["rmax"] + rho)
        & (t >= params["tan_lo"])
        & (t <= params["tan_hi"])
        & (np.abs(z) * cos_hv - h * sin_hv <= rho)
        & (vals >= thr)
    )
    n_bins = int(params["n_bins"])
    n_beams = int(params["n_beams"])
    inv_dr = params["inv_dr"]
    cb = np.clip(np.floor((r - rmin) * inv_dr), 0, n_bins - 1).astype(np.int64)
    cj = beam_index_lo(t, edges)
    count = np.bincount(cb[rivals] * n_beams + cj[rivals], minlength=n_bins * n_beams)
    S_riv = _prefix(count.reshape(n_bins, n_beams))
    S_lit = _prefix((image >= thr).astype(np.int64))
    if arcs is not None:
        from gpumap.layers.viewgain import arc_bits

        seen = v >= 0
        np.bitwise_or.at(arcs, flat[seen], (np.uint16(1) << arc_bits(
            A, x[seen], y[seen], z[seen], h2[seen]).astype(np.uint16)).astype(np.uint16))
    cand = (v >= thr) & (vals >= thr)
    if not cand.any():
        return np.zeros(0, np.int64)
    r, h2, t = r[cand], h2[cand], t[cand]

    def cells(w):
        """Bins and beams within ``w`` of each candidate's range and azimuth arc."""
        b0 = np.clip(np.floor((r - w - rmin) * inv_dr), 0, n_bins - 1).astype(np.int64)
        b1 = np.clip(np.floor((r + w - rmin) * inv_dr), 0, n_bins - 1).astype(np.int64)
        j0, j1 = beam_span(t, h2, w, edges, n_beams)
        return b0, b1, j0, j1

    # the echo: a bright cell within tube_m of the centre; who could have made it: any voxel
    # holding a point there, its centre up to rho (half the cube's diagonal) further
    lit = _rect(S_lit, *cells(_F(tube_m))) > 0
    b0, b1, j0, j1 = cells(_F(tube_m) + rho)
    # the rivals within one voxel of the candidate (itself included) that sit in its tube
    nb = np.asarray(params["box_n"], np.int64)
    loc = idx - params["box_lo"].astype(np.int64)
    ci = np.flatnonzero(cand)
    own = np.zeros(ci.size, np.int64)
    for off in np.ndindex(3, 3, 3):
        q = loc[ci] + (np.array(off) - 1)
        inside = np.all((q >= 0) & (q < nb), axis=1)
        k = np.where(inside, (q[:, 0] * nb[1] + q[:, 1]) * nb[2] + q[:, 2], 0)
        hit = inside & rivals[k] & (cb[k] >= b0) & (cb[k] <= b1) & (cj[k] >= j0) & (cj[k] <= j1)
        own += hit
    alone = (_rect(S_riv, b0, b1, j0, j1) == own) & lit
    return np.sort(flat[cand][alone])


def voxel_states(values: np.ndarray, confirmed: np.ndarray, threshold: float) -> np.ndarray:
    """(n,) uint8 state of each voxel from its map value (``+inf`` unknown) and confirmed flag:
    0 unknown, 1 free, 2 occupied and unconfirmed, 3 occupied and confirmed
    (:meth:`gpumap.MinMaxMapper.confidence`)."""
    out = np.where(np.isinf(values), 0, np.where(values < np.float32(threshold), 1, 2)).astype(np.uint8)
    out[(out == 2) & (confirmed == 1)] = 3
    return out


def check_candidates(T_W_S_candidates: object, unknown_weight: object) -> tuple[np.ndarray, float]:
    """Candidate poses (K, 4, 4) float64 and the weight of unknown voxels for a view gain,
    checked, or raise saying what came."""
    w = check_finite_scalar(unknown_weight, "unknown_weight")
    if w < 0:
        raise ValueError(f"Expected unknown_weight >= 0, but got {w}")
    if isinstance(T_W_S_candidates, np.ma.MaskedArray):
        raise TypeError("Expected a plain array for 'T_W_S_candidates', but got a masked array")
    Ts = np.asarray(T_W_S_candidates)
    if Ts.ndim != 3 or Ts.shape[1:] != (4, 4):
        raise ValueError(f"Expected T_W_S_candidates of shape (K, 4, 4), but got {Ts.shape}")
    return check_poses(Ts), w


class ConfidenceLayer:
    """The confidence layer of a map of ``n_voxels`` (a bounded grid): per voxel, whether a ping
    confirmed it (``confirmed``, uint8 0 or 1) and the elevation-arc directions pings observed it
    along (``arcs``, uint16 masks of :data:`gpumap.layers.viewgain.PAIR_STEPS` bits), both flat in the grid's
    C order, updated by :meth:`confirm` after each ping's update."""

    name = "confidence"
    per_ping = True  # the pass reads the map as each ping left it

    def __init__(self, mapper=None) -> None:
        self._confirmed = np.zeros(0, np.uint8)
        self._arcs = np.zeros(0, np.uint16)
        self.mapper = None
        self._static = None  # (beam edges, the rivals' half aperture, the widened aperture's corners)
        self._gain_runner = None  # made on the first view gain, on the map's backend
        self._device = None  # the pass on a Warp or OpenCL map's device (gpumap.layers.confidence_device)
        self._on_device = False  # the device's arrays are newer than the host's
        self._scalars = None  # (their key, the pass's scalars: gpumap.layers.confidence_device.pass_scalars)
        if mapper is not None:
            mapper.attach(self)

    # ------------------------------------------------------------------ the layer protocol
    def attached(self, mapper) -> None:
        """Bind to ``mapper`` (a bounded GridSpec's; :meth:`gpumap.MinMaxMapper.attach` calls it), taking
        the ``confirmed`` and ``arcs`` a loaded map file kept."""
        if mapper.sparse is not None:
            raise ValueError(
                "Expected a gpumap.MinMaxMapper on a GridSpec for the confidence layer, but this map "
                "allocates blocks on demand (it has no confidence layer yet)"
            )
        if self.mapper is not None:
            raise ValueError("Expected a confidence layer not attached yet, but it follows a map already")
        n = mapper.grid.n_voxels
        self.mapper = mapper
        self._confirmed = np.zeros(n, np.uint8)
        self._arcs = np.zeros(n, np.uint16)
        kept = mapper.layer_state.pop(self.name, None)
        if kept is not None:
            self._confirmed[:] = kept["confirmed"].ravel()
            self._arcs[:] = kept["arcs"].ravel()

    def after_ping(self, mapper, image: np.ndarray, T_W_S: np.ndarray, pad_m: float, params) -> None:
        """The confidence pass of one ping after its update."""
        self.confirm(mapper.integrator, T_W_S, pad_m, image, mapper.raw_values, mapper.grid.voxel_size_m,
                     params)

    def file_arrays(self) -> dict[str, np.ndarray]:
        """``confirmed`` (uint8) and ``arcs`` (uint16), flat over the grid, for the map file."""
        return {"confirmed": self.confirmed, "arcs": self.arcs}

    def states(self) -> np.ndarray:
        """(nx, ny, nz) uint8 state of each voxel: 0 unknown, 1 free, 2 occupied and unconfirmed
        (only consistent with the pings: the elevation stretch lives here), 3 occupied and
        confirmed (some view resolved it in elevation; the exact rule: this module). Occupied means a
        value ``>= threshold``; confidence never changes a value, so it never turns an occupied voxel
        free."""
        m = self._bound()
        with m.storage.lock:
            v = m.raw_values().ravel()
            conf = self.confirmed.copy()
        return voxel_states(v, conf, m.threshold).reshape(m.grid.shape)

    def gains(self, T_W_S_candidates: np.ndarray, unknown_weight: float = 1.0) -> np.ndarray:
        """(K,) float64 gain of each candidate sonar pose ((K, 4, 4) float), from the map alone.

        ``gain = settle + unknown_weight * unknown``: ``settle`` counts the unconfirmed occupied
        voxels the candidate observes along an elevation arc that could settle them: both
        neighbours along the arc known free (a bright echo would confirm them, a dark clear view
        carve them), or, next to free space, an arc direction no ping has observed them along;
        ``unknown`` the never-observed voxels in blocks of 4^3 whose centre it observes (exact
        rules in :mod:`gpumap.layers.viewgain`). Runs on the map's backend; every backend gives the
        NumPy reference's gains exactly. Raises on bad poses, with the map unchanged."""
        m = self._bound()
        Ts, w = check_candidates(T_W_S_candidates, unknown_weight)
        with m.storage.lock:
            return self.view_gain(Ts, w, m.raw_values(), m.threshold, m.grid, m.storage.backend,
                                  m.integrator.params)

    def _bound(self):
        if self.mapper is None:
            raise ValueError("Expected a confidence layer attached to a map (mapper.attach(layer)), but "
                             "this one follows none")
        return self.mapper

    @property
    def confirmed(self) -> np.ndarray:
        """(n,) uint8 0 or 1 per voxel: some ping confirmed it (the host's copy, brought up to date
        from the device on reading; writes into it reach the device before the next pass)."""
        self._to_host()
        return self._confirmed

    @property
    def arcs(self) -> np.ndarray:
        """(n,) uint16 masks of the elevation-arc directions pings observed each voxel along (as
        :attr:`confirmed`, the host's copy)."""
        self._to_host()
        return self._arcs

    def _to_host(self) -> None:
        if self._on_device:
            self._device.download(self._confirmed, self._arcs)
            self._on_device = False

    def reset(self) -> None:
        """Nothing confirmed, no arc observed."""
        self._on_device = False
        self._confirmed[:] = 0
        self._arcs[:] = 0

    def confirm(self, integrator, T: np.ndarray, pad: float, img: np.ndarray, read_values,
                voxel_size_m: float, update_params: np.ndarray | None = None) -> None:
        """The confidence pass of one ping (pose ``T``, footprint pad ``pad`` m, image ``img``),
        after its update: ``integrator`` (:class:`gpumap.core.integrator.Integrator`) makes its record
        (``update_params``: the update's, reused where the rivals' box is the update's),
        ``read_values()`` gives the map's values then (flat or not, ``+inf`` unknown). On a Warp or
        OpenCL map the pass runs on its device (:mod:`gpumap.layers.confidence_device`), after the update
        on the same stream, and reads the map where it lives; on ``numpy``, :func:`confirm_ping`."""
        from gpumap.geometry import beam_tan_edges

        st = integrator.storage
        if self._static is None:
            sp = integrator.spec
            half = min(0.5 * sp.vfov_rad * (1.0 + APERTURE_MARGIN), 0.49 * np.pi)
            wide = SonarSpec(sp.range_min_m, sp.range_max_m, sp.n_bins, sp.bearings_rad, 2.0 * half)
            pts = wide.fov_corners_S()
            # the update's box is the pass's (the backend then holds the ping's image whenever the
            # pass has voxels to walk)
            same = bool(np.array_equal(pts, integrator.fov_pts_S))
            self._static = (beam_tan_edges(sp), half, pts, same)
        edges, half, pts, same = self._static
        # the box that holds the rivals: the widened aperture's
        if same and update_params is not None:
            params = update_params
        else:
            params, _ = integrator.ping_params(T[None], np.array([pad]), fov_pts=pts)
        tube_m = TUBE_VOXELS * voxel_size_m
        if st.backend.name != "numpy" and st.sparse is None:
            from gpumap.layers.confidence_device import DeviceConfidence, pass_scalars

            if self._device is None:
                self._device = DeviceConfidence(st.backend, integrator.spec, self._confirmed.size)
            if not self._on_device:  # the host's arrays (new, read or written since) go first
                self._device.upload(self._confirmed, self._arcs)
                self._on_device = True
            if not same and st.backend.name == "warp-cpu":
                from gpumap.backends.warp_backend import warp_upload_image

                warp_upload_image(st.backend, img)
            vr = st.value_rule
            key = (float(params["rho"][0]), tube_m, vr.carve_views, vr.bright_share, vr.share_z)
            if self._scalars is None or self._scalars[0] != key:
                self._scalars = (key, pass_scalars(integrator.spec, params[0], half, tube_m, vr))
            self._device.run(params[0, ...], self._scalars[1])
            return
        if img.dtype == np.uint8:
            from gpumap.backends import U8_SCALE

            img = img.astype(np.float32) * U8_SCALE
        values = read_values().ravel()
        flat = confirm_ping(params[0], img, edges, values, half, tube_m, self._arcs)
        self._confirmed[flat] = 1

    def view_gain(self, Ts: np.ndarray, unknown_weight: float, values: np.ndarray, threshold: float,
                  grid: GridSpec, backend, params: np.ndarray) -> np.ndarray:
        """(K,) float64 gains of checked candidate poses ``Ts`` (:func:`check_candidates`) against
        the map's ``values`` ((nx, ny, nz) over ``grid``, ``+inf`` unknown), on ``backend`` (the
        map's :class:`gpumap.backends.Backend`), with the map's static ping record ``params``
        (:mod:`gpumap.layers.viewgain`)."""
        from gpumap.layers.viewgain import GainRunner, _fov, gain_points, poses_to_rows

        pts = gain_points(values, self.confirmed.reshape(grid.shape) == 1, threshold, grid, self.arcs)
        if self._gain_runner is None:
            self._gain_runner = GainRunner(backend)
        settle, unknown = self._gain_runner(poses_to_rows(Ts), pts, _fov(params))
        return settle.astype(np.float64) + unknown_weight * unknown.astype(np.float64)


def with_confidence(mapper):
    """``mapper`` with a :class:`ConfidenceLayer` attached (``mapper.layer("confidence")``); returns
    the mapper, so a map and its layer are made in one expression."""
    mapper.attach(ConfidenceLayer())
    return mapper
