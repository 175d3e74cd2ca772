"""Differentiable ping model: Warp kernels that render sonar images from a voxel field.

Device code only (the host side is :mod:`gpumap.layers.render`; the NumPy twin of the forward pass
is :mod:`gpumap.layers.render_reference`). The model, per ping, per elevation ray of a beam, per
range sample ``s`` (sample ``s`` sits at the centre of range cell ``s``)::

    o(x)      trilinear occupancy in [0, 1] (voxel-centred field, 0 outside the grid)
    alpha_s = 1 - exp(-kappa * o(x_s) * ds / h)         opacity of the sample (h: voxel size)
    T_s     = prod_{t < s} (1 - alpha_t)                transmittance to the sample
    cos_s   = |d . grad o| / sqrt(|grad o|^2 + (delta / h)^2)   incidence from the field's gradient
    c_s     = w_ray * L(r_s) * rho(x_s) * (cos_s^2 + eps)^(k / 2)  emission if the ray stops here
    E[s, beam] += T_s * alpha_s * c_s                   summed over the beam's elevation rays

``w_ray = cos(phi) dphi B(phi)`` carries the ray's share of the beam's solid angle per radian of
azimuth and the two-way vertical beam pattern (side lobes included, built on the host).

Kernels, in launch order: :func:`sample_field` (one thread per sample; Warp differentiates it),
:func:`composite` (one thread per ray, a loop along the ray; its adjoint is
:func:`composite_adjoint`, written by hand because Warp does not differentiate loops that carry
state from one iteration to the next), :func:`image_loss` (one thread per image cell; Warp
differentiates it) and :func:`smoothness` (one thread per voxel).
"""

from __future__ import annotations

import warp as wp

# gpumap's mapper turns Warp's adjoints off globally (faster compiles); these kernels need theirs.
wp.set_module_options({"enable_backward": True})


@wp.func
def _occ_at(field: wp.array3d(dtype=wp.float32), i: int, j: int, k: int) -> float:
    if i < 0 or j < 0 or k < 0 or i >= field.shape[0] or j >= field.shape[1] or k >= field.shape[2]:
        return 0.0
    return field[i, j, k]


@wp.kernel
def sample_field(
    occ: wp.array3d(dtype=wp.float32),
    refl: wp.array3d(dtype=wp.float32),
    grid_origin: wp.vec3,
    inv_voxel: float,
    rot_W_S: wp.array(dtype=wp.mat33),
    t_W_S: wp.array(dtype=wp.vec3),
    ray_dir_S: wp.array(dtype=wp.vec3),
    ray_weight: wp.array(dtype=wp.float32),
    range0_m: float,
    step_m: float,
    kappa: float,
    cos_exponent: float,
    spreading_exponent: float,
    absorption_db_per_m: float,
    alpha: wp.array3d(dtype=wp.float32),
    emit: wp.array3d(dtype=wp.float32),
):
    """alpha[p, ray, s], emit[p, ray, s]: opacity and emission of sample ``s`` of ``ray`` in ping ``p``."""
    p, ray, s = wp.tid()
    r = range0_m + (float(s) + 0.5) * step_m
    d = rot_W_S[p] * ray_dir_S[ray]
    x = t_W_S[p] + d * r
    u = (x - grid_origin) * inv_voxel - wp.vec3(0.5, 0.5, 0.5)
    fx = wp.floor(u[0])
    fy = wp.floor(u[1])
    fz = wp.floor(u[2])
    i = int(fx)
    j = int(fy)
    k = int(fz)
    a = u[0] - fx
    b = u[1] - fy
    c = u[2] - fz
    o000 = _occ_at(occ, i, j, k)
    o100 = _occ_at(occ, i + 1, j, k)
    o010 = _occ_at(occ, i, j + 1, k)
    o110 = _occ_at(occ, i + 1, j + 1, k)
    o001 = _occ_at(occ, i, j, k + 1)
    o101 = _occ_at(occ, i + 1, j, k + 1)
    o011 = _occ_at(occ, i, j + 1, k + 1)
    o111 = _occ_at(occ, i + 1, j + 1, k + 1)
    # bilinear in (y, z) at x = 0 and x = 1, etc.: value and the three partial derivatives
    c00 = o000 * (1.0 - a) + o100 * a
    c10 = o010 * (1.0 - a) + o110 * a
    c01 = o001 * (1.0 - a) + o101 * a
    c11 = o011 * (1.0 - a) + o111 * a
    c0 = c00 * (1.0 - b) + c10 * b
    c1 = c01 * (1.0 - b) + c11 * b
    val = c0 * (1.0 - c) + c1 * c
    gz = (c1 - c0) * inv_voxel
    gy = ((c10 - c00) * (1.0 - c) + (c11 - c01) * c) * inv_voxel
    x0 = (o000 * (1.0 - b) + o010 * b) * (1.0 - c) + (o001 * (1.0 - b) + o011 * b) * c
    x1 = (o100 * (1.0 - b) + o110 * b) * (1.0 - c) + (o101 * (1.0 - b) + o111 * b) * c
    gx = (x1 - x0) * inv_voxel
    rho = (
        (
            (_occ_at(refl, i, j, k) * (1.0 - a) + _occ_at(refl, i + 1, j, k) * a) * (1.0 - b)
            + (_occ_at(refl, i, j + 1, k) * (1.0 - a) + _occ_at(refl, i + 1, j + 1, k) * a) * b
        )
        * (1.0 - c)
        + (
            (_occ_at(refl, i, j, k + 1) * (1.0 - a) + _occ_at(refl, i + 1, j, k + 1) * a) * (1.0 - b)
            + (_occ_at(refl, i, j + 1, k + 1) * (1.0 - a) + _occ_at(refl, i + 1, j + 1, k + 1) * a) * b
        )
        * c
    )
    g = wp.vec3(gx, gy, gz)
    dot = wp.dot(d, g)
    delta = 0.1 * inv_voxel
    cos2 = dot * dot / (wp.dot(g, g) + delta * delta)
    shade = wp.pow(cos2 + 1.0e-4, 0.5 * cos_exponent)
    loss = wp.pow(r, -spreading_exponent) * wp.pow(10.0, -0.2 * absorption_db_per_m * (r - 1.0))
    alpha[p, ray, s] = 1.0 - wp.exp(-kappa * val * step_m * inv_voxel)
    emit[p, ray, s] = ray_weight[ray] * loss * rho * shade


@wp.kernel(enable_backward=False)
def composite(
    alpha: wp.array3d(dtype=wp.float32),
    emit: wp.array3d(dtype=wp.float32),
    ray_beam: wp.array(dtype=wp.int32),
    trans: wp.array3d(dtype=wp.float32),
    energy: wp.array3d(dtype=wp.float32),
):
    """energy[p, s, beam] += T_s alpha_s emit_s along each ray; trans[p, ray, s] = T_s (for the adjoint)."""
    p, ray = wp.tid()
    beam = ray_beam[ray]
    t = float(1.0)
    for s in range(alpha.shape[2]):
        a = alpha[p, ray, s]
        trans[p, ray, s] = t
        wp.atomic_add(energy, p, s, beam, t * a * emit[p, ray, s])
        t = t * (1.0 - a)


@wp.kernel(enable_backward=False)
def composite_adjoint(
    alpha: wp.array3d(dtype=wp.float32),
    emit: wp.array3d(dtype=wp.float32),
    ray_beam: wp.array(dtype=wp.int32),
    trans: wp.array3d(dtype=wp.float32),
    energy_grad: wp.array3d(dtype=wp.float32),
    alpha_grad: wp.array3d(dtype=wp.float32),
    emit_grad: wp.array3d(dtype=wp.float32),
):
    """Adjoint of :func:`composite`: with ``g_s = dL/dE[p, s, beam]`` and the suffix sum
    ``S_s = sum_{u > s} g_u c_u alpha_u prod_{s < t < u} (1 - alpha_t)`` (built backwards as
    ``S_{s-1} = g_s c_s alpha_s + (1 - alpha_s) S_s``): ``dL/dc_s = g_s T_s alpha_s`` and
    ``dL/dalpha_s = T_s (g_s c_s - S_s)``. No division by ``1 - alpha``: exact at alpha = 1."""
    p, ray = wp.tid()
    beam = ray_beam[ray]
    acc = float(0.0)
    n = alpha.shape[2]
    for q in range(n):
        s = n - 1 - q
        a = alpha[p, ray, s]
        c = emit[p, ray, s]
        t = trans[p, ray, s]
        g = energy_grad[p, s, beam]
        emit_grad[p, ray, s] = emit_grad[p, ray, s] + g * t * a
        alpha_grad[p, ray, s] = alpha_grad[p, ray, s] + t * (g * c - acc)
        acc = g * c * a + (1.0 - a) * acc


@wp.kernel
def image_loss(
    energy: wp.array3d(dtype=wp.float32),
    measured: wp.array3d(dtype=wp.float32),
    weight: wp.array3d(dtype=wp.float32),
    display: wp.array(dtype=wp.float32),
    huber_delta: float,
    scale: float,
    power: float,
    predicted: wp.array3d(dtype=wp.float32),
    loss: wp.array(dtype=wp.float32),
):
    """predicted = floor + (1 - floor)(1 - exp(-exp(log_gain) E)), ``display = (log_gain, floor)``;
    loss += scale * weight * huber((predicted + 1e-3)^power - (measured + 1e-3)^power)
    (``power`` 0.5 compares square roots: a dim echo weighs nearly as much as a bright one)."""
    p, i, j = wp.tid()
    f = display[1]
    pred = f + (1.0 - f) * (1.0 - wp.exp(-wp.exp(display[0]) * energy[p, i, j]))
    predicted[p, i, j] = pred
    r = wp.abs(wp.pow(pred + 1.0e-3, power) - wp.pow(measured[p, i, j] + 1.0e-3, power))
    h = float(0.0)
    if r <= huber_delta:
        h = 0.5 * r * r
    else:
        h = huber_delta * (r - 0.5 * huber_delta)
    wp.atomic_add(loss, 0, scale * weight[p, i, j] * h)


@wp.kernel
def smoothness(
    field: wp.array3d(dtype=wp.float32),
    active: wp.array3d(dtype=wp.uint8),
    scale: float,
    sparsity: float,
    loss: wp.array(dtype=wp.float32),
):
    """loss += scale * sum over the +x, +y, +z neighbours of (f_v - f_n)^2, for pairs of active voxels
    (a fixed voxel does not pull its free neighbours towards its value), + sparsity * f_v per active voxel."""
    i, j, k = wp.tid()
    nx = field.shape[0]
    ny = field.shape[1]
    nz = field.shape[2]
    v = field[i, j, k]
    act = active[i, j, k] != wp.uint8(0)
    total = float(0.0)
    if i + 1 < nx:
        if act and active[i + 1, j, k] != wp.uint8(0):
            dx = v - field[i + 1, j, k]
            total = total + dx * dx
    if j + 1 < ny:
        if act and active[i, j + 1, k] != wp.uint8(0):
            dy = v - field[i, j + 1, k]
            total = total + dy * dy
    if k + 1 < nz:
        if act and active[i, j, k + 1] != wp.uint8(0):
            dz = v - field[i, j, k + 1]
            total = total + dz * dz
    if act:
        total = total * scale + sparsity * v
    else:
        total = total * scale
    wp.atomic_add(loss, 0, total)


@wp.kernel(enable_backward=False)
def adam_project(
    param: wp.array(dtype=wp.float32),
    grad: wp.array(dtype=wp.float32),
    m: wp.array(dtype=wp.float32),
    v: wp.array(dtype=wp.float32),
    lower: wp.array(dtype=wp.float32),
    upper: wp.array(dtype=wp.float32),
    lr: float,
    beta1: float,
    beta2: float,
    bias1: float,
    bias2: float,
):
    """One Adam step on ``param`` then projection onto ``[lower, upper]`` (the hard constraints)."""
    i = wp.tid()
    g = grad[i]
    mi = beta1 * m[i] + (1.0 - beta1) * g
    vi = beta2 * v[i] + (1.0 - beta2) * g * g
    m[i] = mi
    v[i] = vi
    step = lr * (mi / bias1) / (wp.sqrt(vi / bias2) + 1.0e-8)
    param[i] = wp.clamp(param[i] - step, lower[i], upper[i])
