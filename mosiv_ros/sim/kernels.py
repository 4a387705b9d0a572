"""The MLS-MPM substep as Warp kernels, one per phase: P2G, grid update, G2P; and a state check.

Moving least squares MPM (Hu et al. 2018, "A moving least squares material point method",
Sec. 4 and Algorithm 1) with quadratic B-spline weights (Stomakhin et al. 2013 / mpm.graphics
Eq. 123) and APIC affine velocity fields C (Jiang et al. 2015). Layouts:

- particles: index b * N + p for batch b and particle p; ``obj[p]`` is the object index 0..K-1;
- grid: one field per object (multi-field MPM), index (b * K + k) * G + node, with
  node = (i * ny + j) * nz + l on a dense nx * ny * nz grid of spacing dx whose node (0, 0, 0) is
  at ``lo``.

Kernel parameters are named for where the simulator finds their values (``simulator._bind``):
``src_x``, ``dst_b``, ... a field of a particle state, ``grid_m``, ... of the substep's grid,
``collider_pos``, ... of the colliders, ``E``, ``ground_height``, ... a parameter's replicas,
and sizes and geometry (``n_particles``, ``dims``, ``lo``, ``dx``, ...) by name. Each batch
row's substep and its substeps a frame are read from ``own_dt`` and ``own_substeps``, never
passed as values, so that a captured CUDA graph of some substeps serves every time step, and
rows at their own time steps alike (``simulator.graph_runs``).
docs/simulator.md maps the substep onto the method.

**Contact between objects** (multi-velocity-field MPM, Bardenhagen et al. 2001, "An improved
contact algorithm for the material point method"; Huang et al. 2011): each object scatters to its
own field, so objects do not stick together as on a single grid. At a node where two or more
fields have mass, every field k is compared with the centre-of-mass velocity v_cm of all fields.
As in Bardenhagen et al., one body's normal serves the pair: the unit mass gradient (central
differences of the grid mass) of the present field of the largest object (highest
``normal_rank``), so that a small
object's corners sliding on a large one do not tilt the normal (a corner's gradient would read
tangential sliding as approach and lift the small object). n_k points from k into that object
(out of it, for the object itself). When k approaches the others, dn = (v_k - v_cm) . n_k > 0, its
normal relative velocity is removed and its tangential relative velocity t shrinks by
mu * dn (Coulomb), or vanishes (stick) when |t| <= mu * dn; otherwise k separates freely. The
friction coefficient is the mass-weighted mean over the other fields of the pair rule
mu_kl = (mu_k + mu_l) / 2 (MOSIV), exactly mu_kl for two objects. For two objects the two
corrections are equal and opposite, so momentum is conserved.

Everything here is differentiable on a ``wp.Tape``: outputs go to fresh arrays and the only
accumulations are ``wp.atomic_add``. The backward pass runs Warp's adjoints, except G2P's, the
grid update's and P2G's with one thread a particle, which are written out (``g2p_adjoint``,
``p2g_adjoint_kernel``: Warp's kept 251-255 registers live on a GPU; ``grid_update_kernels``), and P2G's
scatter with three threads a particle, whose adjoint Warp calls in place of its own
(``scatter_plane``'s). Tests hold each written adjoint to the one Warp generates from the same
forward function, which therefore stays differentiable by Warp. Warp's adjoint of a loop whose
bound is known only at run time gets a differentiable value the loop carries wrong (a sum over
a node's fields came out inf and NaN), so ``grid_update`` is built for the scene's object
count, and its differentiable sums over a node's fields are loops over that constant, unrolled
(``grid_update_kernels``); it runs one thread per field node. The loops over a node's fields
that give only thresholds and integers (``node_total``, ``present_fields``) sit in functions,
whose calls the adjoint replays as the forward ran them. The grid pass launches over
a box of nodes (``field_node``): the whole grid, or on the CPU, where every thread costs, the
nodes the particles' stencils can reach (``Simulator._active_box``).
"""

from __future__ import annotations

import functools

import warp as wp

from mosiv_ros.sim.boundaries import WALL_CELLS
from mosiv_ros.sim.materials import (
    kirchhoff_stress,
    kirchhoff_stress_adjoint,
    lame_adjoint,
    return_mapping,
    return_mapping_adjoint,
)
from mosiv_ros.sim.params import add_param, lane_particle, param
from mosiv_ros.sim.warp_reduce import add, clear_node, run_start, scatter

MAX_COLLIDERS = 2
WALL = wp.constant(WALL_CELLS)
CONTACT_MASS_FRACTION = wp.constant(1.0e-3)
# Grid nodes less than this fraction of a cell above the ground plane count as on it (their
# velocity is projected like that of nodes below it). Domains snap to multiples of dx, so a
# floor at such a height runs through a layer of nodes whose float32 position lands a rounding
# error above or below it depending on the domain's corner: without the tolerance, two
# simulations of one scene in different domains treated that layer differently (6 cm apart
# after 8 frames of a bouncing ball).
GROUND_SNAP = wp.constant(1.0e-3)
# warps of a Warp launch's thread block (Warp 1.4 launches blocks of 256 threads)
BLOCK_WARPS = wp.constant(8)


@wp.func
def node_index(i: int, j: int, l: int, dims: wp.vec3i):
    return (i * dims[1] + j) * dims[2] + l


@wp.func
def field_node(t: int, box_lo: wp.vec3i, box_dims: wp.vec3i, dims: wp.vec3i):
    """Field-node index of thread ``t`` of a launch over a box of nodes in every field.

    The launch has one thread per node of the box (``box_dims`` nodes from ``box_lo``) in each
    (batch, object) field, field-major; the whole grid is the box (0, 0, 0) + ``dims``, where
    the thread's index is the node's, found without integer divisions (on a GPU these took a
    fifth of the grid passes' time over the mostly empty grids of a search batch).
    """
    if box_lo[0] == 0 and box_lo[1] == 0 and box_lo[2] == 0 and box_dims[0] == dims[0] and (
            box_dims[1] == dims[1] and box_dims[2] == dims[2]):
        return t
    n_box = box_dims[0] * box_dims[1] * box_dims[2]
    r = t % n_box
    return (t // n_box) * dims[0] * dims[1] * dims[2] + node_index(
        box_lo[0] + r // (box_dims[1] * box_dims[2]), box_lo[1] + (r // box_dims[2]) % box_dims[1],
        box_lo[2] + r % box_dims[2], dims)


@wp.func
def block_particle(t: int, block_warps: int, n_lanes: int):
    """The particle thread ``t`` runs when each 256-thread block runs ``block_warps`` warps of them.

    -1: none (a warp past ``block_warps`` in its block, or a thread past the ``n_lanes``
    particles). With 8 warps (every thread) thread t runs particle t; fewer spread a small
    launch over more blocks, so over more multiprocessors (``Simulator._spread``).
    """
    i = t
    if block_warps < BLOCK_WARPS:
        within = t % (BLOCK_WARPS * 32)
        i = (t // (BLOCK_WARPS * 32)) * block_warps * 32 + within
        if within >= block_warps * 32:
            i = -1
    if i >= n_lanes:
        i = -1
    return i


@wp.func
def stencil_base(x: wp.vec3, lo: wp.vec3, inv_dx: float, dims: wp.vec3i):
    """Lower corner of the 3x3x3 quadratic stencil, clamped inside the grid."""
    X = (x - lo) * inv_dx
    return wp.vec3i(
        wp.clamp(int(wp.floor(X[0] - 0.5)), 0, dims[0] - 3),
        wp.clamp(int(wp.floor(X[1] - 0.5)), 0, dims[1] - 3),
        wp.clamp(int(wp.floor(X[2] - 0.5)), 0, dims[2] - 3),
    )


@wp.func
def bspline_weights(fx: float):
    """Quadratic B-spline weights at offsets 0, 1, 2 for fractional position fx in [0.5, 1.5)."""
    return wp.vec3(
        0.5 * (1.5 - fx) * (1.5 - fx),
        0.75 - (fx - 1.0) * (fx - 1.0),
        0.5 * (fx - 0.5) * (fx - 0.5),
    )


@wp.func
def own_turn(own_substeps: wp.array(dtype=int), batch: int, substep: int):
    """Whether row ``batch`` takes substep ``substep`` of the frame (every row does at one time step)."""
    return substep < own_substeps[batch]


@wp.func
def scatter_plane(grid_m: wp.array(dtype=float), grid_p: wp.array(dtype=wp.vec3), a: int, w_a: float,
                  wy: wp.vec3, wz: wp.vec3, mass: float, at_origin: wp.vec3, per_x: wp.vec3,
                  per_y: wp.vec3, per_z: wp.vec3, offset: int, base: wp.vec3i, dims: wp.vec3i, run: int):
    """P2G's scatter to the nine nodes of plane ``a`` of a particle's stencil, whose x weight is ``w_a``.

    A node's momentum is w (m v + affine dpos) with dpos = (o - fx) dx at offset o: ``at_origin``
    the part at o = (0, 0, 0), ``per_x``, ... the affine matrix's columns times dx, per unit offset.
    """
    for c in range(3):
        for e in range(3):
            weight = w_a * wy[c] * wz[e]
            node = offset + node_index(base[0] + a, base[1] + c, base[2] + e, dims)
            p_node = at_origin + per_x * float(a) + per_y * float(c) + per_z * float(e)
            scatter(grid_m, grid_p, node, c * 3 + e, dims[2], run, weight * mass, p_node * weight)


@wp.func_replay(scatter_plane)
def _replay_scatter_plane(grid_m: wp.array(dtype=float), grid_p: wp.array(dtype=wp.vec3), a: int,
                          w_a: float, wy: wp.vec3, wz: wp.vec3, mass: float, at_origin: wp.vec3,
                          per_x: wp.vec3, per_y: wp.vec3, per_z: wp.vec3, offset: int, base: wp.vec3i,
                          dims: wp.vec3i, run: int):
    """The backward pass replays P2G without scattering again: the grid holds the forward's sums."""
    pass


@wp.func_grad(scatter_plane)
def _adjoint_scatter_plane(grid_m: wp.array(dtype=float), grid_p: wp.array(dtype=wp.vec3), a: int,
                           w_a: float, wy: wp.vec3, wz: wp.vec3, mass: float, at_origin: wp.vec3,
                           per_x: wp.vec3, per_y: wp.vec3, per_z: wp.vec3, offset: int, base: wp.vec3i,
                           dims: wp.vec3i, run: int):
    """The adjoint of ``scatter_plane``: the nine nodes' adjoints gathered and summed as read.

    Warp's own adjoint of the unrolled loop keeps every node's intermediates live until its
    reverse sweep: P2G's adjoint spilled its 255 registers a thread and took 2.7 times as long
    on an H200 (docs/simulator.md, "On a GPU"). Here a node's adjoints (gm, gp) fold into sums
    at once: with weight = w_a wy[c] wz[e] and p_node as in the forward,
    d/d weight = gm mass + gp . p_node, d/d mass = sum weight gm, and p_node's adjoint
    weight gp goes to at_origin and, times the node's offset along each axis, to per_x, per_y, per_z.
    """
    adj_m = wp.adjoint[grid_m]
    adj_p = wp.adjoint[grid_p]
    if adj_m.shape[0] > 0:
        d_w_a = float(0.0)
        d_mass = float(0.0)
        d_wy = wp.vec3(0.0)
        d_wz = wp.vec3(0.0)
        moved = wp.vec3(0.0)  # sum of weight gp
        along_y = wp.vec3(0.0)  # sum of c weight gp
        along_z = wp.vec3(0.0)  # sum of e weight gp
        for c in range(3):
            for e in range(3):
                node = offset + node_index(base[0] + a, base[1] + c, base[2] + e, dims)
                gm = adj_m[node]
                gp = adj_p[node]
                w_yz = wy[c] * wz[e]
                weight = w_a * w_yz
                p_node = at_origin + per_x * float(a) + per_y * float(c) + per_z * float(e)
                d_weight = gm * mass + wp.dot(gp, p_node)
                d_w_a += d_weight * w_yz
                d_wy[c] = d_wy[c] + d_weight * w_a * wz[e]
                d_wz[e] = d_wz[e] + d_weight * w_a * wy[c]
                d_mass += weight * gm
                moved += gp * weight
                along_y += gp * (weight * float(c))
                along_z += gp * (weight * float(e))
        wp.adjoint[w_a] += d_w_a
        wp.adjoint[wy] += d_wy
        wp.adjoint[wz] += d_wz
        wp.adjoint[mass] += d_mass
        wp.adjoint[at_origin] += moved
        wp.adjoint[per_x] += moved * float(a)
        wp.adjoint[per_y] += along_y
        wp.adjoint[per_z] += along_z


def _p2g(planes: int) -> wp.Kernel:
    """``p2g`` with a particle's stencil split over ``planes`` threads (1 or 3), a constant of its code.

    With 3, each of a particle's threads scatters the nine nodes of one plane of its stencil
    (a = 0, 1, 2 along x), and each computes the particle's deformation and stress itself; only
    the first writes the particle's b, so that its adjoint is read once. The threads are
    plane-major (``plane_threads`` a plane), so a warp's lanes scatter one plane and their runs
    (``warp_reduce``) still share nodes. On a GPU a sample scene's few thousand particles leave
    nearly every multiprocessor idle, and a launch takes as long as one thread's chain of work:
    three shorter chains side by side cost less than one long one, the stress computed three
    times included (``Simulator._spread`` picks the planes, ``simulator._p2g_planes``; one on
    the CPU, where every thread costs). With one thread a particle its adjoint is written out
    (``p2g_adjoint_kernel``), so Warp generates one only for three. Each is a Warp module of its
    own, so that processes build them side by side on an empty kernel cache (``runtime.build_aside``).
    """

    def p2g(
        src_x: wp.array(dtype=wp.vec3),
        src_v: wp.array(dtype=wp.vec3),
        src_C: wp.array(dtype=wp.mat33),
        src_b: wp.array(dtype=wp.mat33),
        volume: wp.array(dtype=float),
        grid_tau: wp.array(dtype=wp.mat33),
        obj: wp.array(dtype=int),
        family: wp.array(dtype=int),
        E: wp.array(dtype=float),
        nu: wp.array(dtype=float),
        yield_stress: wp.array(dtype=float),
        friction_angle: wp.array(dtype=float),
        bulk_modulus: wp.array(dtype=float),
        viscosity: wp.array(dtype=float),
        density: wp.array(dtype=float),
        n_particles: int,
        plane_threads: int,
        part: int,
        parts: int,
        plane_warps: int,
        n_objects: int,
        n_nodes: int,
        dims: wp.vec3i,
        lo: wp.vec3,
        dx: float,
        own_dt: wp.array(dtype=float),
        own_substeps: wp.array(dtype=int),
        substep: int,
        dst_b: wp.array(dtype=wp.mat33),
        grid_m: wp.array(dtype=float),
        grid_p: wp.array(dtype=wp.vec3),
    ):
        """Deformation update, return mapping, stress, and scatter of mass and momentum.

        The forward pass runs as one part (``parts`` = 1). The adjoint writes each particle's own
        gradients and its replica of each parameter's, so on the CPU it runs in parts side by side
        (``params.lane_particle``).
        """
        t = wp.tid()
        plane = t // plane_threads  # 0 where ``planes`` is 1: the launch has plane_threads threads
        i = block_particle(lane_particle(t - plane * plane_threads, part, parts), plane_warps, src_x.shape[0])
        if i < 0:
            return
        batch = i // n_particles
        if not own_turn(own_substeps, batch, substep):  # a row whose frame is done: its state stays
            if plane == 0:
                dst_b[i] = src_b[i]
            return
        h = own_dt[batch]
        k = obj[i - batch * n_particles]
        q = batch * n_objects + k
        fam = family[k]
        # each particle array is read once: every read is an atomic add of its adjoint
        x_i = src_x[i]
        C_i = src_C[i]
        # b <- f b f^T with f = I + h C (Hu et al. 2018, Eq. 17 applied to b = F F^T; h the row's dt)
        f = wp.identity(n=3, dtype=float) + C_i * h
        b_trial = f * src_b[i] * wp.transpose(f)
        E_q = param(E, q, i)
        nu_q = param(nu, q, i)
        b_new = return_mapping(fam, b_trial, E_q, nu_q, param(yield_stress, q, i),
                               param(friction_angle, q, i))
        if plane == 0:  # one thread writes the particle's state, so its adjoint is read once
            dst_b[i] = b_new
        tau = kirchhoff_stress(fam, b_new, C_i, E_q, nu_q, param(bulk_modulus, q, i),
                               param(viscosity, q, i))
        if grid_tau.shape[0] > 0:
            tau = tau + grid_tau[i]
        inv_dx = 1.0 / dx
        vol = volume[i]
        mass = param(density, q, i) * vol
        # MLS-MPM fused momentum/stress scatter (Hu et al. 2018, Eq. 29): D^-1 = 4 / dx^2
        affine = tau * (-h * vol * 4.0 * inv_dx * inv_dx) + C_i * mass
        base = stencil_base(x_i, lo, inv_dx, dims)
        fx = (x_i - lo) * inv_dx - wp.vec3(float(base[0]), float(base[1]), float(base[2]))
        wx = bspline_weights(fx[0])
        wy = bspline_weights(fx[1])
        wz = bspline_weights(fx[2])
        offset = q * n_nodes
        moved = affine * dx  # per unit offset along each axis, a column (``scatter_plane``)
        at_origin = src_v[i] * mass - moved * fx
        per_x = wp.vec3(moved[0, 0], moved[1, 0], moved[2, 0])
        per_y = wp.vec3(moved[0, 1], moved[1, 1], moved[2, 1])
        per_z = wp.vec3(moved[0, 2], moved[1, 2], moved[2, 2])
        # neighbouring lanes with the same stencil add once per node (sim.warp_reduce)
        run = run_start(offset + node_index(base[0], base[1], base[2], dims))
        if wp.static(planes == 1):
            for a in range(3):
                scatter_plane(grid_m, grid_p, a, wx[a], wy, wz, mass, at_origin, per_x, per_y, per_z,
                              offset, base, dims, run)
        else:
            scatter_plane(grid_m, grid_p, plane, wx[plane], wy, wz, mass, at_origin, per_x, per_y, per_z,
                          offset, base, dims, run)

    module = wp.context.get_module(f"{__name__}.{'p2g' if planes == 1 else 'p2g_planes'}")
    return wp.Kernel(p2g, key="p2g", module=module, options={"enable_backward": planes == 3})


p2g = _p2g(1)
p2g_planes = _p2g(3)


@wp.func
def divide(a: wp.vec3, s: float):
    """The quotient a / s (s > 0) by components: the same float32 values, a finite adjoint.

    Warp's adjoint of ``vec3 / float`` takes -(a . adj) / (s * s), and s * s underflows in
    float32 (to zero below s ~ 3e-23, to a denormal of few bits below 1e-19). Grid masses that
    small are real: a particle d cells short of a half-cell point puts 0.5 d^2 of its weight on
    the node across, and d ~ 1e-6 along two axes leaves 1e-25 of its mass there (particles of a
    settled sand pile creep across such points along x and y at once on the pile's diagonals).
    The adjoint was then inf, or 0 / 0, and every gradient of the rollout NaN. A float
    division's adjoint is -(adj (a / s)) / s: the quotient comes first, so it stays finite
    whenever the quotient is (for p / m it is adj v / m, and the adj v a node gathers from its
    particles scales with the mass it holds from them).
    """
    return wp.vec3(a[0] / s, a[1] / s, a[2] / s)


@wp.func
def field_velocity(
    grid_m: wp.array(dtype=float),
    grid_p: wp.array(dtype=wp.vec3),
    grid_a: wp.array(dtype=wp.vec3),
    uniform: wp.array(dtype=float),
    batch: int,
    index: int,
    dt: float,
):
    """Grid velocity of one field at one node after the effects' accelerations: p/m + dt (g + a).

    ``uniform``: the replicas of the batches' summed uniform accelerations g (``Simulator``);
    ``grid_a`` is empty when no effect adds accelerations at nodes.
    """
    m = grid_m[index]
    vel = wp.vec3(0.0)
    if m > 0.0:
        acceleration = wp.vec3(param(uniform, 3 * batch, index), param(uniform, 3 * batch + 1, index),
                               param(uniform, 3 * batch + 2, index))
        if grid_a.shape[0] > 0:
            acceleration = acceleration + grid_a[index]
        vel = divide(grid_p[index], m) + acceleration * dt
    return vel


@wp.func
def difference_nodes(i: int, j: int, l: int, dims: wp.vec3i):
    """The nodes below and above (i, j, l) along each axis that ``mass_gradient`` differences (clamped to the grid)."""
    return (wp.vec3i(wp.max(i - 1, 0), wp.max(j - 1, 0), wp.max(l - 1, 0)),
            wp.vec3i(wp.min(i + 1, dims[0] - 1), wp.min(j + 1, dims[1] - 1), wp.min(l + 1, dims[2] - 1)))


@wp.func
def mass_gradient(grid_m: wp.array(dtype=float), offset: int, i: int, j: int, l: int,
                  dims: wp.vec3i, inv_dx: float):
    """Central-difference gradient of one field's grid mass (one-sided at the domain faces)."""
    below, above = difference_nodes(i, j, l, dims)
    gx = (grid_m[offset + node_index(above[0], j, l, dims)]
          - grid_m[offset + node_index(below[0], j, l, dims)]) / float(above[0] - below[0])
    gy = (grid_m[offset + node_index(i, above[1], l, dims)]
          - grid_m[offset + node_index(i, below[1], l, dims)]) / float(above[1] - below[1])
    gz = (grid_m[offset + node_index(i, j, above[2], dims)]
          - grid_m[offset + node_index(i, j, below[2], dims)]) / float(above[2] - below[2])
    return wp.vec3(gx, gy, gz) * inv_dx


@wp.func
def coulomb(v_rel: wp.vec3, n: wp.vec3, friction: float):
    """Coulomb projection of a relative velocity moving into a surface of outward normal n.

    Returns v_rel unchanged when separating (v_rel . n >= 0); otherwise removes the normal part
    and shrinks the tangential part by friction * |normal part|, to zero if that is larger.
    """
    vn = wp.dot(v_rel, n)
    result = v_rel
    if vn < 0.0:
        vt = v_rel - n * vn
        t = wp.length(vt)
        remaining = t + wp.max(friction, 0.0) * vn  # <= t; > 0 only if t > 0
        if remaining <= 0.0:
            result = wp.vec3(0.0)
        else:
            result = vt * (remaining / t)
    return result


@wp.func
def collider_sdf(shape: int, size: wp.vec3, p: wp.vec3):
    """Signed distance (x) and outward unit normal (yzw) of a collider in its own frame."""
    d = float(0.0)
    n = wp.vec3(0.0, 0.0, 1.0)
    if shape == 0:  # sphere of radius size[0]
        r = wp.length(p)
        d = r - size[0]
        if r > 0.0:
            n = p / r
    elif shape == 1:  # box of half extents size
        qx = wp.abs(p[0]) - size[0]
        qy = wp.abs(p[1]) - size[1]
        qz = wp.abs(p[2]) - size[2]
        outside = wp.vec3(wp.max(qx, 0.0), wp.max(qy, 0.0), wp.max(qz, 0.0))
        lo = wp.length(outside)
        inside = wp.min(wp.max(qx, wp.max(qy, qz)), 0.0)
        d = lo + inside
        if lo > 0.0:
            n = wp.vec3(wp.sign(p[0]) * outside[0], wp.sign(p[1]) * outside[1],
                        wp.sign(p[2]) * outside[2]) / lo
        elif qx >= qy and qx >= qz:
            n = wp.vec3(wp.sign(p[0]), 0.0, 0.0)
        elif qy >= qz:
            n = wp.vec3(0.0, wp.sign(p[1]), 0.0)
        else:
            n = wp.vec3(0.0, 0.0, wp.sign(p[2]))
    else:  # capsule: radius size[0], half length size[1] along z
        axis_point = wp.vec3(0.0, 0.0, wp.clamp(p[2], -size[1], size[1]))
        r = wp.length(p - axis_point)
        d = r - size[0]
        if r > 0.0:
            n = (p - axis_point) / r
    return wp.vec4(d, n[0], n[1], n[2])


@wp.func
def node_total(grid_m: wp.array(dtype=float), first: int, n_nodes: int, n_objects: int):
    """Total mass of all object fields at one node; ``first`` is the node's index in field 0.

    Its loop carries a value, which Warp's adjoint of a loop gets wrong (module docstring); it
    is right here because the loop is a function's: the adjoint replays the call as the forward
    ran it, and the sum is only a threshold, so no gradient flows back through the loop.
    """
    total = float(0.0)
    for k in range(n_objects):
        total = total + grid_m[first + k * n_nodes]
    return total


@wp.func
def present_fields(grid_m: wp.array(dtype=float), first: int, n_nodes: int, n_objects: int,
                   threshold: float, normal_rank: wp.array(dtype=int)):
    """How many fields hold more than ``threshold`` at a node, and the highest normal_rank of them.

    A function for the reason ``node_total`` is one; both results are integers.
    """
    count = int(0)
    lead_rank = int(0)
    for k in range(n_objects):
        if grid_m[first + k * n_nodes] > threshold:
            count = count + 1
            lead_rank = wp.max(lead_rank, normal_rank[k])
    return wp.vec2i(count, lead_rank)


@wp.func
def node_place(index: int, objects: int, n_nodes: int, dims: wp.vec3i, lo: wp.vec3, dx: float):
    """Field node ``index``'s batch row, object, node, the node's (i, j, l) and its position."""
    batch = index // (objects * n_nodes)
    k = (index // n_nodes) % objects
    node = index % n_nodes
    i = node // (dims[1] * dims[2])
    j = (node // dims[2]) % dims[1]
    l = node % dims[2]
    return batch, k, node, i, j, l, lo + wp.vec3(float(i), float(j), float(l)) * dx


@wp.func
def coulomb_adjoint(v_rel: wp.vec3, n: wp.vec3, friction: float, adj: wp.vec3):
    """The adjoints of ``coulomb``'s v_rel, n and friction, given the adjoint ``adj`` of its result."""
    vn = wp.dot(v_rel, n)
    adj_v = adj
    adj_n = wp.vec3(0.0)
    adj_friction = float(0.0)
    if vn < 0.0:
        adj_v = wp.vec3(0.0)
        vt = v_rel - n * vn
        t = wp.length(vt)
        mu = wp.max(friction, 0.0)
        remaining = t + mu * vn
        if remaining > 0.0:  # the result vt * (remaining / t)
            scale = remaining / t
            adj_scale = wp.dot(vt, adj)
            adj_remaining = adj_scale / t
            adj_t = adj_remaining - adj_scale * scale / t
            adj_vn = adj_remaining * mu
            if friction > 0.0:
                adj_friction = adj_remaining * vn
            adj_vt = adj * scale + vt * (adj_t / t)
            # vt = v_rel - n vn, vn = v_rel . n
            adj_vn = adj_vn - wp.dot(adj_vt, n)
            adj_v = adj_vt + n * adj_vn
            adj_n = v_rel * adj_vn - adj_vt * vn
    return adj_v, adj_n, adj_friction


@wp.func
def add_field_velocity_adjoint(grid_m: wp.array(dtype=float), grid_p: wp.array(dtype=wp.vec3),
                               adj_grid_m: wp.array(dtype=float), adj_grid_p: wp.array(dtype=wp.vec3),
                               adj_grid_a: wp.array(dtype=wp.vec3), adj_uniform: wp.array(dtype=float),
                               batch: int, index: int, dt: float, adj_v: wp.vec3, adj_m: float):
    """Add the adjoints of ``field_velocity``'s inputs for the adjoint ``adj_v`` of its result.

    ``adj_m``: more of the node's mass adjoint, added with its own.
    """
    m = grid_m[index]
    adj_mass = adj_m
    if m > 0.0:
        adj_mass = adj_mass - wp.dot(adj_v, divide(grid_p[index], m)) / m
        wp.atomic_add(adj_grid_p, index, divide(adj_v, m))
        adj_a = adj_v * dt
        if adj_uniform.shape[0] > 0:
            for c in range(3):
                add_param(adj_uniform, 3 * batch + c, index, adj_a[c])
        if adj_grid_a.shape[0] > 0:
            wp.atomic_add(adj_grid_a, index, adj_a)
    wp.atomic_add(adj_grid_m, index, adj_mass)


@wp.func
def add_mass_gradient_adjoint(adj_grid_m: wp.array(dtype=float), offset: int, i: int, j: int, l: int,
                              dims: wp.vec3i, inv_dx: float, adj_g: wp.vec3):
    """Add the adjoints of the masses ``mass_gradient`` read, given the adjoint ``adj_g`` of its result."""
    below, above = difference_nodes(i, j, l, dims)
    a = adj_g * inv_dx
    ax = a[0] / float(above[0] - below[0])
    ay = a[1] / float(above[1] - below[1])
    az = a[2] / float(above[2] - below[2])
    wp.atomic_add(adj_grid_m, offset + node_index(above[0], j, l, dims), ax)
    wp.atomic_add(adj_grid_m, offset + node_index(below[0], j, l, dims), -ax)
    wp.atomic_add(adj_grid_m, offset + node_index(i, above[1], l, dims), ay)
    wp.atomic_add(adj_grid_m, offset + node_index(i, below[1], l, dims), -ay)
    wp.atomic_add(adj_grid_m, offset + node_index(i, j, above[2], dims), az)
    wp.atomic_add(adj_grid_m, offset + node_index(i, j, below[2], dims), -az)


@wp.func
def ground_plane(ground_height: wp.array(dtype=float), ground_normal: wp.array(dtype=float), batch: int,
                 index: int, x_node: wp.vec3, dx: float):
    """The ground's unit normal, its parameters' normal vector, and whether node ``x_node`` is on the ground."""
    raw = wp.vec3(param(ground_normal, 3 * batch, index), param(ground_normal, 3 * batch + 1, index),
                  param(ground_normal, 3 * batch + 2, index))
    n = wp.normalize(raw)
    on = int(0)
    if wp.dot(n, x_node) - param(ground_height, batch, index) < GROUND_SNAP * dx:
        on = 1
    return n, raw, on


@wp.func
def collider_surface(c: int, substep: int, collider_count: int, x_node: wp.vec3, collider_shape: wp.array(dtype=int),
                     collider_size: wp.array(dtype=wp.vec3), collider_pos: wp.array(dtype=wp.vec3),
                     collider_rot: wp.array(dtype=wp.quat), collider_vel: wp.array(dtype=wp.vec3),
                     collider_omega: wp.array(dtype=wp.vec3)):
    """Whether node ``x_node`` lies inside collider ``c`` at ``substep``, with its outward normal and velocity there."""
    inside = int(0)
    normal = wp.vec3(0.0)
    v_col = wp.vec3(0.0)
    if c < collider_count:
        row = substep * collider_count + c
        r = x_node - collider_pos[row]
        local = wp.quat_rotate_inv(collider_rot[row], r)
        sd = collider_sdf(collider_shape[c], collider_size[c], local)
        if sd[0] < 0.0:
            inside = 1
            normal = wp.quat_rotate(collider_rot[row], wp.vec3(sd[1], sd[2], sd[3]))
            v_col = collider_vel[row] + wp.cross(collider_omega[row], r)
    return inside, normal, v_col


@wp.func
def wall_mask(vel: wp.vec3, i: int, j: int, l: int, dims: wp.vec3i):
    """1 for each velocity component the slip walls keep at node (i, j, l), 0 for one into a face within WALL nodes."""
    mask = wp.vec3(1.0)
    if (i < WALL and vel[0] < 0.0) or (i >= dims[0] - WALL and vel[0] > 0.0):
        mask[0] = 0.0
    if (j < WALL and vel[1] < 0.0) or (j >= dims[1] - WALL and vel[1] > 0.0):
        mask[1] = 0.0
    if (l < WALL and vel[2] < 0.0) or (l >= dims[2] - WALL and vel[2] > 0.0):
        mask[2] = 0.0
    return mask


@functools.cache
def grid_update_kernels(colliders: int, objects: int) -> tuple[wp.Kernel, wp.Kernel]:
    """``grid_update`` and its written adjoint for ``objects`` objects and at most ``colliders`` colliders.

    Both counts are constants of their code, and each such pair is a Warp module of its own,
    built when a scene first needs it (``Simulator``; one module of every variant would rebuild
    all of them for each new one).

    - The sums over a node's fields (the object contact's centre of mass) are unrolled over the
      ``objects`` fields (module docstring); a lone object's kernels have no contact code.
    - The colliders' projections are unrolled too. Warp's adjoint of the grid update (before the
      written one) kept their intermediates live: on an H200 it took 246 registers a thread and
      15.7-16.3 us a launch of a sample scene's grid with two colliders' code, 120 and
      11.4-12.1 us without (benchmarks/RESULTS.md, "The search's closest ends raced in step").
      So a scene without colliders asks for 0.
    """
    key = f"grid_update_{colliders}_{objects}"
    module = wp.context.get_module(f"{__name__}.{key}")
    module.options["max_unroll"] = max(objects, colliders, module.options.get("max_unroll", 0))

    def contact_sums(grid_m: wp.array(dtype=float), grid_p: wp.array(dtype=wp.vec3), grid_a: wp.array(dtype=wp.vec3),
                     uniform: wp.array(dtype=float), friction: wp.array(dtype=float), batch: int, first: int,
                     n_nodes: int, present: float, dt: float):
        """The sums over the fields present at a node: mass, momentum after the effects (m v), mu m."""
        m_total = float(0.0)
        p_total = wp.vec3(0.0)
        mu_total = float(0.0)
        for other in range(objects):  # unrolled: a constant
            at = first + other * n_nodes
            m_other = grid_m[at]
            if m_other > present:
                m_total = m_total + m_other
                p_total = p_total + field_velocity(grid_m, grid_p, grid_a, uniform, batch, at, dt) * m_other
                mu_total = mu_total + param(friction, batch * objects + other, at) * m_other
        return m_total, p_total, mu_total

    def add_contact_sums_adjoint(grid_m: wp.array(dtype=float), grid_p: wp.array(dtype=wp.vec3),
                                 grid_a: wp.array(dtype=wp.vec3), uniform: wp.array(dtype=float),
                                 friction: wp.array(dtype=float), adj_grid_m: wp.array(dtype=float),
                                 adj_grid_p: wp.array(dtype=wp.vec3), adj_grid_a: wp.array(dtype=wp.vec3),
                                 adj_uniform: wp.array(dtype=float), adj_friction: wp.array(dtype=float),
                                 batch: int, first: int, n_nodes: int, present: float, dt: float,
                                 adj_m_total: float, adj_p_total: wp.vec3, adj_mu_total: float):
        """Add the adjoints of ``contact_sums``' inputs, given those of its three sums."""
        for other in range(objects):
            at = first + other * n_nodes
            m_other = grid_m[at]
            if m_other > present:
                mu_other = param(friction, batch * objects + other, at)
                if adj_friction.shape[0] > 0:
                    add_param(adj_friction, batch * objects + other, at, adj_mu_total * m_other)
                v_other = field_velocity(grid_m, grid_p, grid_a, uniform, batch, at, dt)
                add_field_velocity_adjoint(grid_m, grid_p, adj_grid_m, adj_grid_p, adj_grid_a, adj_uniform, batch, at,
                                           dt, adj_p_total * m_other,
                                           adj_m_total + wp.dot(adj_p_total, v_other) + adj_mu_total * mu_other)

    def object_contact(grid_m: wp.array(dtype=float), grid_p: wp.array(dtype=wp.vec3), grid_a: wp.array(dtype=wp.vec3),
                       uniform: wp.array(dtype=float), friction: wp.array(dtype=float),
                       normal_rank: wp.array(dtype=int), ranked_object: wp.array(dtype=int), batch: int, k: int,
                       node: int, index: int, i: int, j: int, l: int, n_nodes: int, dims: wp.vec3i, dx: float,
                       dt: float, vel: wp.vec3):
        """The velocity ``vel`` of field k at a node after the object contact there, and what its adjoint needs.

        Returns the velocity; 1 if the field approached the others and was projected (else 0);
        the sign that turns the lead field's mass gradient into k's outward normal n (-1 when k
        is the lead); the lead field's offset and mass gradient; the node's index in field 0;
        the mass a field needs to be present; n; the sums of mass and mu m over the fields
        present; k's friction, the pair's, and the centre-of-mass velocity v_cm.
        """
        m = grid_m[index]
        first = batch * objects * n_nodes + node
        present = node_total(grid_m, first, n_nodes, objects) * CONTACT_MASS_FRACTION
        fields = present_fields(grid_m, first, n_nodes, objects, present, normal_rank)
        touching = int(0)
        sign = float(1.0)
        lead_offset = int(0)
        g_lead = wp.vec3(0.0)
        n = wp.vec3(0.0)
        m_total = float(0.0)
        mu_total = float(0.0)
        mu_k = float(0.0)
        mu_pair = float(0.0)
        v_cm = wp.vec3(0.0)
        out = vel
        if fields[0] > 1 and m > present:
            lead = ranked_object[fields[1]]
            lead_offset = (batch * objects + lead) * n_nodes
            g_lead = mass_gradient(grid_m, lead_offset, i, j, l, dims, 1.0 / dx)
            g_len = wp.length(g_lead)
            if k == lead:  # the outward normal of k towards the others: into the lead, or out of it
                sign = -1.0
            if g_len > 0.0:
                n = divide(g_lead, g_len) * sign  # at a fringe of the lead object g_len is tiny too
                m_total, p_total, mu_total = sums(grid_m, grid_p, grid_a, uniform, friction, batch, first, n_nodes,
                                                  present, dt)
                mu_k = param(friction, batch * objects + k, index)
                mu_pair = 0.5 * (mu_k + (mu_total - mu_k * m) / (m_total - m))
                v_cm = divide(p_total, m_total)
                rel = vel - v_cm
                if wp.dot(rel, n) > 0.0:
                    # approaching: the others are a surface of outward normal -n
                    touching = 1
                    out = v_cm + coulomb(rel, -n, mu_pair)
        return out, touching, sign, lead_offset, g_lead, first, present, n, m_total, mu_total, mu_k, mu_pair, v_cm

    def collider_projections(vel: wp.vec3, count: int, substep: int, collider_count: int, x_node: wp.vec3,
                             collider_shape: wp.array(dtype=int), collider_size: wp.array(dtype=wp.vec3),
                             collider_friction: wp.array(dtype=float), collider_pos: wp.array(dtype=wp.vec3),
                             collider_rot: wp.array(dtype=wp.quat), collider_vel: wp.array(dtype=wp.vec3),
                             collider_omega: wp.array(dtype=wp.vec3)):
        """``vel`` after the projections onto the first ``count`` colliders, in order."""
        out = vel
        for c in range(colliders):  # unrolled: a constant
            if c < count:
                inside, normal, v_col = collider_surface(c, substep, collider_count, x_node, collider_shape,
                                                         collider_size, collider_pos, collider_rot, collider_vel,
                                                         collider_omega)
                if inside != 0:
                    out = v_col + coulomb(out - v_col, normal, collider_friction[c])
        return out

    sums = wp.Function(contact_sums, key=f"contact_sums_{objects}", namespace="", module=module)
    sums_adjoint = wp.Function(add_contact_sums_adjoint, key=f"add_contact_sums_adjoint_{objects}",
                               namespace="", module=module)
    contact = wp.Function(object_contact, key=f"object_contact_{objects}", namespace="", module=module)
    projected = wp.Function(collider_projections, key=f"collider_projections_{colliders}", namespace="",
                            module=module)

    def grid_update(
        grid_m: wp.array(dtype=float),
        grid_p: wp.array(dtype=wp.vec3),
        grid_a: wp.array(dtype=wp.vec3),
        uniform: wp.array(dtype=float),
        friction: wp.array(dtype=float),
        normal_rank: wp.array(dtype=int),
        ranked_object: wp.array(dtype=int),
        ground_height: wp.array(dtype=float),
        ground_normal: wp.array(dtype=float),
        ground_friction: wp.array(dtype=float),
        has_ground: int,
        collider_shape: wp.array(dtype=int),
        collider_size: wp.array(dtype=wp.vec3),
        collider_friction: wp.array(dtype=float),
        collider_pos: wp.array(dtype=wp.vec3),
        collider_rot: wp.array(dtype=wp.quat),
        collider_vel: wp.array(dtype=wp.vec3),
        collider_omega: wp.array(dtype=wp.vec3),
        substep: int,
        collider_count: int,
        n_nodes: int,
        dims: wp.vec3i,
        box_lo: wp.vec3i,
        box_dims: wp.vec3i,
        lo: wp.vec3,
        dx: float,
        own_dt: wp.array(dtype=float),
        grid_v: wp.array(dtype=wp.vec3),
    ):
        """Velocity of one object field at one node: effects, object contact, ground, colliders, walls.

        The object contact reads every field at the node: the count of fields present and the
        largest of them (``present_fields``), and their sums of mass, momentum after the effects
        (m v) and friction-weighted mass (mu m). A field is present when it holds more than
        CONTACT_MASS_FRACTION of the node's mass: the far fringe of an object's kernel support,
        and M-PhyGs boundary particles outside the surface (whose volume fades to 1e-4 of a
        particle's), take no part in contact.
        """
        index = field_node(wp.tid(), box_lo, box_dims, dims)
        m = grid_m[index]
        if m <= 0.0:
            # a particle's stencil reads an empty field node only at a weight of zero, and grid_v
            # there is zero (or is grid_p, zero here), or on a grid that G2P clears a finite
            # velocity of an earlier substep of the rollout (simulator._Grid)
            return
        batch, k, node, i, j, l, x_node = node_place(index, objects, n_nodes, dims, lo, dx)
        dt = own_dt[batch]
        vel = field_velocity(grid_m, grid_p, grid_a, uniform, batch, index, dt)

        if wp.static(objects > 1):
            vel, touching, sign, lead_offset, g_lead, first, present, n, m_total, mu_total, mu_k, mu_pair, v_cm = (
                contact(grid_m, grid_p, grid_a, uniform, friction, normal_rank, ranked_object, batch, k, node, index,
                        i, j, l, n_nodes, dims, dx, dt, vel))
        if has_ground != 0:
            n_ground, raw, on = ground_plane(ground_height, ground_normal, batch, index, x_node, dx)
            if on != 0:
                vel = coulomb(vel, n_ground, param(ground_friction, batch, index))
        vel = projected(vel, colliders, substep, collider_count, x_node, collider_shape, collider_size,
                        collider_friction, collider_pos, collider_rot, collider_vel, collider_omega)
        # slip walls: no velocity into a domain face within WALL nodes of it
        grid_v[index] = wp.cw_mul(vel, wall_mask(vel, i, j, l, dims))

    def grid_update_adjoint(
        grid_m: wp.array(dtype=float),
        grid_p: wp.array(dtype=wp.vec3),
        grid_a: wp.array(dtype=wp.vec3),
        uniform: wp.array(dtype=float),
        friction: wp.array(dtype=float),
        normal_rank: wp.array(dtype=int),
        ranked_object: wp.array(dtype=int),
        ground_height: wp.array(dtype=float),
        ground_normal: wp.array(dtype=float),
        ground_friction: wp.array(dtype=float),
        has_ground: int,
        collider_shape: wp.array(dtype=int),
        collider_size: wp.array(dtype=wp.vec3),
        collider_friction: wp.array(dtype=float),
        collider_pos: wp.array(dtype=wp.vec3),
        collider_rot: wp.array(dtype=wp.quat),
        collider_vel: wp.array(dtype=wp.vec3),
        collider_omega: wp.array(dtype=wp.vec3),
        substep: int,
        collider_count: int,
        n_nodes: int,
        dims: wp.vec3i,
        box_lo: wp.vec3i,
        box_dims: wp.vec3i,
        lo: wp.vec3,
        dx: float,
        own_dt: wp.array(dtype=float),
        grid_v: wp.array(dtype=wp.vec3),
        adj_grid_m: wp.array(dtype=float),
        adj_grid_p: wp.array(dtype=wp.vec3),
        adj_grid_a: wp.array(dtype=wp.vec3),
        adj_uniform: wp.array(dtype=float),
        adj_friction: wp.array(dtype=float),
        adj_ground_normal: wp.array(dtype=float),
        adj_ground_friction: wp.array(dtype=float),
        adj_grid_v: wp.array(dtype=wp.vec3),
    ):
        """The adjoint of ``grid_update``, written out: adds to the adjoints of its inputs as Warp's would.

        The first arguments are ``grid_update``'s, then the adjoints (``.grad``) of its arrays
        that carry one (the colliders' arrays and the ground's height, read only in tests, carry
        none). The node's velocity is computed again as the forward did, keeping the input of
        each projection; the adjoint then runs through them last first. Every adjoint is added
        atomically: a field node's contact adds to the other fields' nodes and, through the
        contact normal, to the lead field's neighbours. Warp's generated adjoint replayed the
        whole forward with every intermediate live (148 registers a thread on an H200, and the
        costliest kernel of a sample bag's backward substep, benchmarks/RESULTS.md).
        """
        index = field_node(wp.tid(), box_lo, box_dims, dims)
        m = grid_m[index]
        if m <= 0.0:
            return
        batch, k, node, i, j, l, x_node = node_place(index, objects, n_nodes, dims, lo, dx)
        dt = own_dt[batch]
        vel = field_velocity(grid_m, grid_p, grid_a, uniform, batch, index, dt)
        v_field = vel
        if wp.static(objects > 1):  # the object contact, and what its adjoint needs
            vel, touching, sign, lead_offset, g_lead, first, present, n, m_total, mu_total, mu_k, mu_pair, v_cm = (
                contact(grid_m, grid_p, grid_a, uniform, friction, normal_rank, ranked_object, batch, k, node, index,
                        i, j, l, n_nodes, dims, dx, dt, v_field))
        v_contact = vel
        on = int(0)
        n_ground = wp.vec3(0.0)
        raw = wp.vec3(0.0)
        mu_ground = float(0.0)
        if has_ground != 0:
            n_ground, raw, on = ground_plane(ground_height, ground_normal, batch, index, x_node, dx)
            if on != 0:
                mu_ground = param(ground_friction, batch, index)
                vel = coulomb(vel, n_ground, mu_ground)
        v_ground = vel
        vel = projected(v_ground, colliders, substep, collider_count, x_node, collider_shape, collider_size,
                        collider_friction, collider_pos, collider_rot, collider_vel, collider_omega)

        adj = wp.cw_mul(adj_grid_v[index], wall_mask(vel, i, j, l, dims))
        for last in range(colliders):  # the colliders last first, each one's input found again
            c = colliders - 1 - last
            v_in = projected(v_ground, c, substep, collider_count, x_node, collider_shape, collider_size,
                             collider_friction, collider_pos, collider_rot, collider_vel, collider_omega)
            inside, normal, v_col = collider_surface(c, substep, collider_count, x_node, collider_shape, collider_size,
                                                     collider_pos, collider_rot, collider_vel, collider_omega)
            if inside != 0:
                adj_rel, adj_normal, adj_mu = coulomb_adjoint(v_in - v_col, normal, collider_friction[c], adj)
                adj = adj_rel
        if on != 0:
            adj_v, adj_n, adj_mu = coulomb_adjoint(v_contact, n_ground, mu_ground, adj)
            adj = adj_v
            if adj_ground_friction.shape[0] > 0:
                add_param(adj_ground_friction, batch, index, adj_mu)
            if adj_ground_normal.shape[0] > 0:  # through n = raw / |raw|
                adj_raw = (adj_n - n_ground * wp.dot(n_ground, adj_n)) / wp.length(raw)
                for d in range(3):
                    add_param(adj_ground_normal, 3 * batch + d, index, adj_raw[d])
        adj_m = float(0.0)
        if wp.static(objects > 1):
            if touching != 0:
                # vel = v_cm + coulomb(rel, -n, mu_pair) with rel = v_field - v_cm
                adj_rel, adj_minus_n, adj_pair = coulomb_adjoint(v_field - v_cm, -n, mu_pair, adj)
                adj_cm = adj - adj_rel
                adj = adj_rel
                # mu_pair = (mu_k + (mu_total - mu_k m) / (m_total - m)) / 2
                rest = m_total - m
                others = (mu_total - mu_k * m) / rest
                if adj_friction.shape[0] > 0:
                    add_param(adj_friction, batch * objects + k, index, 0.5 * adj_pair * (1.0 - m / rest))
                adj_m = 0.5 * adj_pair * (others - mu_k) / rest
                # v_cm = p_total / m_total
                adj_p_total = divide(adj_cm, m_total)
                adj_m_total = -0.5 * adj_pair * others / rest - wp.dot(adj_cm, v_cm) / m_total
                sums_adjoint(grid_m, grid_p, grid_a, uniform, friction, adj_grid_m, adj_grid_p, adj_grid_a,
                             adj_uniform, adj_friction, batch, first, n_nodes, present, dt, adj_m_total, adj_p_total,
                             0.5 * adj_pair / rest)
                # n = sign g / |g|, g the lead field's mass gradient
                g_len = wp.length(g_lead)
                n_unit = divide(g_lead, g_len)
                adj_unit = -adj_minus_n * sign
                add_mass_gradient_adjoint(adj_grid_m, lead_offset, i, j, l, dims, 1.0 / dx,
                                          divide(adj_unit - n_unit * wp.dot(n_unit, adj_unit), g_len))
        add_field_velocity_adjoint(grid_m, grid_p, adj_grid_m, adj_grid_p, adj_grid_a, adj_uniform, batch, index, dt,
                                   adj, adj_m)

    return (wp.Kernel(grid_update, key=key, module=module, options={"enable_backward": False}),
            wp.Kernel(grid_update_adjoint, key=f"{key}_adjoint", module=module, options={"enable_backward": False}))


@wp.kernel(enable_backward=False)
def g2p(
    src_x: wp.array(dtype=wp.vec3),
    src_v: wp.array(dtype=wp.vec3),
    src_C: wp.array(dtype=wp.mat33),
    grid_v: wp.array(dtype=wp.vec3),
    grid_m: wp.array(dtype=float),
    grid_p: wp.array(dtype=wp.vec3),
    grid_a: wp.array(dtype=wp.vec3),
    grid_tau: wp.array(dtype=wp.mat33),
    grid_clears: int,
    obj: wp.array(dtype=int),
    ground_height: wp.array(dtype=float),
    ground_normal: wp.array(dtype=float),
    has_ground: int,
    n_particles: int,
    block_warps: int,
    n_objects: int,
    n_nodes: int,
    dims: wp.vec3i,
    lo: wp.vec3,
    dx: float,
    own_dt: wp.array(dtype=float),
    own_substeps: wp.array(dtype=int),
    substep: int,
    dst_x: wp.array(dtype=wp.vec3),
    dst_v: wp.array(dtype=wp.vec3),
    dst_C: wp.array(dtype=wp.mat33),
):
    """Gather velocity and affine field from the particle's own object field and advect.

    The particle is also kept on or above the ground plane. A row whose frame is done (rows at
    their own time steps) keeps its state. Where ``grid_clears`` (a grid without gradients on a
    GPU, ``simulator._Grid``) it also clears its stress and the masses, momenta and
    accelerations of its stencil's nodes for the next substep. Its adjoint is ``g2p_adjoint``:
    Warp's is not generated (it would only lengthen this module's build; the test that holds
    ``g2p_adjoint`` to it builds its own).
    """
    i = block_particle(wp.tid(), block_warps, src_x.shape[0])
    if i < 0:
        return
    if grid_clears != 0 and grid_tau.shape[0] > 0:
        grid_tau[i] = wp.mat33(0.0)
    batch = i // n_particles
    if not own_turn(own_substeps, batch, substep):
        dst_x[i] = src_x[i]
        dst_v[i] = src_v[i]
        dst_C[i] = src_C[i]
        return
    k = obj[i - batch * n_particles]
    inv_dx = 1.0 / dx
    x_i = src_x[i]  # read once: every read is an atomic add of its adjoint
    base = stencil_base(x_i, lo, inv_dx, dims)
    fx = (x_i - lo) * inv_dx - wp.vec3(float(base[0]), float(base[1]), float(base[2]))
    wx = bspline_weights(fx[0])
    wy = bspline_weights(fx[1])
    wz = bspline_weights(fx[2])
    offset = (batch * n_objects + k) * n_nodes
    new_v = wp.vec3(0.0)
    # APIC / MLS affine field (Hu et al. 2018, Eq. 28), D^-1 = 4 / dx^2: C = D^-1 sum w g dpos^T
    # with dpos = (o - fx) dx for the node at offset o, summed as D^-1 dx (sum w g o^T - v fx^T)
    moment_x = wp.vec3(0.0)  # sum w g o_x, a column of sum w g o^T
    moment_y = wp.vec3(0.0)
    moment_z = wp.vec3(0.0)
    for a in range(3):
        for c in range(3):
            for e in range(3):
                node = offset + node_index(base[0] + a, base[1] + c, base[2] + e, dims)
                g_w = grid_v[node] * (wx[a] * wy[c] * wz[e])
                new_v += g_w
                moment_x += g_w * float(a)
                moment_y += g_w * float(c)
                moment_z += g_w * float(e)
                if grid_clears != 0:
                    clear_node(grid_m, grid_p, node)
                    if grid_a.shape[0] > 0:
                        grid_a[node] = wp.vec3(0.0)
    new_C = (wp.mat33(moment_x[0], moment_y[0], moment_z[0], moment_x[1], moment_y[1], moment_z[1],
                      moment_x[2], moment_y[2], moment_z[2]) - wp.outer(new_v, fx)) * (4.0 * inv_dx)
    x_new = x_i + new_v * own_dt[batch]
    if has_ground != 0:
        # The grid condition acts at nodes, up to a cell below the plane; a particle that ends
        # a substep below the plane is put back onto it and loses its velocity into it, so
        # soft materials (fluid, sand) cannot settle into the floor.
        n = wp.normalize(wp.vec3(param(ground_normal, 3 * batch, i),
                                 param(ground_normal, 3 * batch + 1, i),
                                 param(ground_normal, 3 * batch + 2, i)))
        phi = wp.dot(n, x_new) - param(ground_height, batch, i)
        if phi < 0.0:
            x_new = x_new - n * phi
            vn = wp.dot(new_v, n)
            if vn < 0.0:
                new_v = new_v - n * vn
    dst_v[i] = new_v
    dst_C[i] = new_C
    dst_x[i] = x_new


@wp.func
def bspline_slopes(fx: float):
    """Derivatives of ``bspline_weights`` with respect to fx."""
    return wp.vec3(fx - 1.5, 2.0 - 2.0 * fx, fx - 0.5)


@wp.kernel(enable_backward=False)
def g2p_adjoint(
    src_x: wp.array(dtype=wp.vec3),
    src_v: wp.array(dtype=wp.vec3),
    src_C: wp.array(dtype=wp.mat33),
    grid_v: wp.array(dtype=wp.vec3),
    grid_m: wp.array(dtype=float),
    grid_p: wp.array(dtype=wp.vec3),
    grid_a: wp.array(dtype=wp.vec3),
    grid_tau: wp.array(dtype=wp.mat33),
    grid_clears: int,
    obj: wp.array(dtype=int),
    ground_height: wp.array(dtype=float),
    ground_normal: wp.array(dtype=float),
    has_ground: int,
    n_particles: int,
    block_warps: int,
    n_objects: int,
    n_nodes: int,
    dims: wp.vec3i,
    lo: wp.vec3,
    dx: float,
    own_dt: wp.array(dtype=float),
    own_substeps: wp.array(dtype=int),
    substep: int,
    dst_x: wp.array(dtype=wp.vec3),
    dst_v: wp.array(dtype=wp.vec3),
    dst_C: wp.array(dtype=wp.mat33),
    adj_src_x: wp.array(dtype=wp.vec3),
    adj_src_v: wp.array(dtype=wp.vec3),
    adj_src_C: wp.array(dtype=wp.mat33),
    adj_grid_v: wp.array(dtype=wp.vec3),
    adj_ground_height: wp.array(dtype=float),
    adj_ground_normal: wp.array(dtype=float),
    adj_dst_x: wp.array(dtype=wp.vec3),
    adj_dst_v: wp.array(dtype=wp.vec3),
    adj_dst_C: wp.array(dtype=wp.mat33),
):
    """The adjoint of ``g2p``, written out: adds to the adjoints of its inputs as Warp's would.

    The first arguments are ``g2p``'s, then the adjoints (``.grad``) of its arrays that carry
    one. Warp's generated adjoint replays the forward with every intermediate of the 27 unrolled
    nodes kept live (255 registers on a GPU, with spills); here the nodes are read again in one
    loop that keeps only the running sums, and each node's velocity adjoint is added once per
    run of lanes (``sim.warp_reduce``). The forward's velocity sum is gathered again only where
    a ground plane may have moved the particle.
    """
    i = block_particle(wp.tid(), block_warps, src_x.shape[0])
    if i < 0:
        return
    batch = i // n_particles
    if not own_turn(own_substeps, batch, substep):
        adj_src_x[i] = adj_src_x[i] + adj_dst_x[i]
        adj_src_v[i] = adj_src_v[i] + adj_dst_v[i]
        adj_src_C[i] = adj_src_C[i] + adj_dst_C[i]
        return
    k = obj[i - batch * n_particles]
    inv_dx = 1.0 / dx
    x_i = src_x[i]
    base = stencil_base(x_i, lo, inv_dx, dims)
    fx = (x_i - lo) * inv_dx - wp.vec3(float(base[0]), float(base[1]), float(base[2]))
    wx = bspline_weights(fx[0])
    wy = bspline_weights(fx[1])
    wz = bspline_weights(fx[2])
    offset = (batch * n_objects + k) * n_nodes
    step = own_dt[batch]
    adj_v = adj_dst_v[i]  # of the gathered velocity, once the ground's projection is undone
    adj_x = adj_dst_x[i]  # of the advected position x + step v, likewise
    if has_ground != 0:
        new_v = wp.vec3(0.0)
        for a in range(3):
            for c in range(3):
                for e in range(3):
                    node = offset + node_index(base[0] + a, base[1] + c, base[2] + e, dims)
                    new_v += grid_v[node] * (wx[a] * wy[c] * wz[e])
        x_new = x_i + new_v * step
        raw = wp.vec3(param(ground_normal, 3 * batch, i), param(ground_normal, 3 * batch + 1, i),
                      param(ground_normal, 3 * batch + 2, i))
        n = wp.normalize(raw)
        phi = wp.dot(n, x_new) - param(ground_height, batch, i)
        if phi < 0.0:
            adj_n = wp.vec3(0.0)
            vn = wp.dot(new_v, n)
            if vn < 0.0:  # v' = v - n (v . n)
                adj_vn = -wp.dot(n, adj_v)
                adj_n = adj_n - adj_v * vn + new_v * adj_vn
                adj_v = adj_v + n * adj_vn
            # x' = x - n phi, phi = n . x - height
            adj_phi = -wp.dot(n, adj_x)
            adj_n = adj_n - adj_x * phi + x_new * adj_phi
            adj_x = adj_x + n * adj_phi
            if adj_ground_height.shape[0] > 0:
                add_param(adj_ground_height, batch, i, -adj_phi)
            if adj_ground_normal.shape[0] > 0:  # through n = raw / |raw|
                adj_raw = (adj_n - n * wp.dot(n, adj_n)) / wp.length(raw)
                for d in range(3):
                    add_param(adj_ground_normal, 3 * batch + d, i, adj_raw[d])
    adj_v = adj_v + adj_x * step
    # C = D^-1 sum w g dpos^T: node g's adjoint is w (adj_v + adj_C dpos), dpos = (o - fx) dx,
    # with adj_C dpos = adj_C o dx - adj_C fx dx summed by the offset's components
    adj_C = adj_dst_C[i] * (4.0 * inv_dx)
    adj_o = adj_v - adj_C * fx  # at offset (0, 0, 0)
    adj_c0 = wp.vec3(adj_C[0, 0], adj_C[1, 0], adj_C[2, 0])  # per unit offset along x
    adj_c1 = wp.vec3(adj_C[0, 1], adj_C[1, 1], adj_C[2, 1])
    adj_c2 = wp.vec3(adj_C[0, 2], adj_C[1, 2], adj_C[2, 2])
    adj_wx = wp.vec3(0.0)
    adj_wy = wp.vec3(0.0)
    adj_wz = wp.vec3(0.0)
    gathered = wp.vec3(0.0)  # sum w g, whose fx part of C gives fx's adjoint
    run = run_start(offset + node_index(base[0], base[1], base[2], dims))
    for a in range(3):
        for c in range(3):
            for e in range(3):
                weight = wx[a] * wy[c] * wz[e]
                node = offset + node_index(base[0] + a, base[1] + c, base[2] + e, dims)
                g_v = grid_v[node]
                adj_g = adj_o + adj_c0 * float(a) + adj_c1 * float(c) + adj_c2 * float(e)
                add(adj_grid_v, node, run, adj_g * weight)
                adj_w = wp.dot(adj_g, g_v)
                gathered += g_v * weight
                adj_wx[a] = adj_wx[a] + adj_w * wy[c] * wz[e]
                adj_wy[c] = adj_wy[c] + adj_w * wx[a] * wz[e]
                adj_wz[e] = adj_wz[e] + adj_w * wx[a] * wy[c]
    adj_fx = wp.vec3(wp.dot(adj_wx, bspline_slopes(fx[0])), wp.dot(adj_wy, bspline_slopes(fx[1])),
                     wp.dot(adj_wz, bspline_slopes(fx[2]))) - wp.transpose(adj_C) * gathered
    adj_src_x[i] = adj_src_x[i] + adj_x + adj_fx * inv_dx


@wp.func
def add_material_param(grads: wp.array(dtype=float), index: int, tid: int, value: float):
    """``add_param`` where the gradient is kept and ``value`` is not zero (a family's unused parameters)."""
    if grads.shape[0] > 0 and value != 0.0:
        add_param(grads, index, tid, value)


@wp.func
def particle_stress(family: int, C: wp.mat33, b: wp.mat33, h: float, E: float, nu: float, yield_stress: float,
                    friction_angle: float, bulk_modulus: float, viscosity: float):
    """P2G's Kirchhoff stress of a particle from its state before the substep (its written adjoint's first part)."""
    f = wp.identity(n=3, dtype=float) + C * h
    b_new = return_mapping(family, f * b * wp.transpose(f), E, nu, yield_stress, friction_angle)
    return kirchhoff_stress(family, b_new, C, E, nu, bulk_modulus, viscosity)


@functools.cache
def p2g_adjoint_kernel(only: int) -> wp.Kernel:
    """``p2g``'s written adjoint for particles of one family (its ``materials.FAMILY_CODES`` code), or of any (-1).

    Built for one family, the other families' code is left out: for the elastic family, nvcc
    for sm_90 puts it at 128 registers a thread, against 168 for every family, so that two
    256-thread blocks fit a multiprocessor. Each variant is a Warp module of its own, built when
    a scene first needs it (``Simulator``), as ``grid_update_kernels``' are.
    """
    key = f"p2g_adjoint_{only}" if only >= 0 else "p2g_adjoint_any"
    module = wp.context.get_module(f"{__name__}.{key}")

    def p2g_adjoint(
        src_x: wp.array(dtype=wp.vec3),
        src_v: wp.array(dtype=wp.vec3),
        src_C: wp.array(dtype=wp.mat33),
        src_b: wp.array(dtype=wp.mat33),
        volume: wp.array(dtype=float),
        grid_tau: wp.array(dtype=wp.mat33),
        obj: wp.array(dtype=int),
        family: wp.array(dtype=int),
        E: wp.array(dtype=float),
        nu: wp.array(dtype=float),
        yield_stress: wp.array(dtype=float),
        friction_angle: wp.array(dtype=float),
        bulk_modulus: wp.array(dtype=float),
        viscosity: wp.array(dtype=float),
        density: wp.array(dtype=float),
        n_particles: int,
        plane_threads: int,
        part: int,
        parts: int,
        plane_warps: int,
        n_objects: int,
        n_nodes: int,
        dims: wp.vec3i,
        lo: wp.vec3,
        dx: float,
        own_dt: wp.array(dtype=float),
        own_substeps: wp.array(dtype=int),
        substep: int,
        dst_b: wp.array(dtype=wp.mat33),
        grid_m: wp.array(dtype=float),
        grid_p: wp.array(dtype=wp.vec3),
        adj_src_x: wp.array(dtype=wp.vec3),
        adj_src_v: wp.array(dtype=wp.vec3),
        adj_src_C: wp.array(dtype=wp.mat33),
        adj_src_b: wp.array(dtype=wp.mat33),
        adj_volume: wp.array(dtype=float),
        adj_grid_tau: wp.array(dtype=wp.mat33),
        adj_E: wp.array(dtype=float),
        adj_nu: wp.array(dtype=float),
        adj_yield_stress: wp.array(dtype=float),
        adj_friction_angle: wp.array(dtype=float),
        adj_bulk_modulus: wp.array(dtype=float),
        adj_viscosity: wp.array(dtype=float),
        adj_density: wp.array(dtype=float),
        adj_dst_b: wp.array(dtype=wp.mat33),
        adj_grid_m: wp.array(dtype=float),
        adj_grid_p: wp.array(dtype=wp.vec3),
    ):
        """The adjoint of ``p2g`` (one thread a particle), written out: adds to its inputs' adjoints as Warp's would.

        The first arguments are ``p2g``'s, then the adjoints (``.grad``) of its arrays that carry
        one. Warp's generated adjoint replays the particle's update and keeps its intermediates
        for the reverse sweep: 255 registers a thread on a GPU, one 256-thread block a
        multiprocessor. Here the stress is computed first and the stencil's node adjoints gathered
        into running sums (as ``scatter_plane``'s adjoint does); then the particle's state is read
        again for the material update's adjoint (``materials.return_mapping_adjoint``,
        ``kirchhoff_stress_adjoint``), so that the state does not stay live across the gather. The
        particle's own adjoints are added without atomics: one thread writes them (on the CPU the
        parts of a launch take disjoint particles, ``params.lane_particle``). P2G with three
        threads a particle (``p2g_planes``) keeps Warp's adjoint.
        """
        i = block_particle(lane_particle(wp.tid(), part, parts), plane_warps, src_x.shape[0])
        if i < 0:
            return
        batch = i // n_particles
        if not own_turn(own_substeps, batch, substep):
            adj_src_b[i] = adj_src_b[i] + adj_dst_b[i]
            return
        h = own_dt[batch]
        k = obj[i - batch * n_particles]
        q = batch * n_objects + k
        if wp.static(only >= 0):  # the family a constant of the code: the others' code left out
            fam = wp.static(only)
        else:
            fam = family[k]
        x_i = src_x[i]
        C_i = src_C[i]
        inv_dx = 1.0 / dx
        vol = volume[i]
        rho = param(density, q, i)
        mass = rho * vol
        tau = particle_stress(fam, C_i, src_b[i], h, param(E, q, i), param(nu, q, i), param(yield_stress, q, i),
                              param(friction_angle, q, i), param(bulk_modulus, q, i), param(viscosity, q, i))
        if grid_tau.shape[0] > 0:
            tau = tau + grid_tau[i]
        stress_scale = -h * 4.0 * inv_dx * inv_dx  # affine = tau stress_scale vol + C mass
        moved = (tau * (stress_scale * vol) + C_i * mass) * dx
        base = stencil_base(x_i, lo, inv_dx, dims)
        fx = (x_i - lo) * inv_dx - wp.vec3(float(base[0]), float(base[1]), float(base[2]))
        wx = bspline_weights(fx[0])
        wy = bspline_weights(fx[1])
        wz = bspline_weights(fx[2])
        offset = q * n_nodes
        v_i = src_v[i]
        at_origin = v_i * mass - moved * fx
        per_x = wp.vec3(moved[0, 0], moved[1, 0], moved[2, 0])
        per_y = wp.vec3(moved[0, 1], moved[1, 1], moved[2, 1])
        per_z = wp.vec3(moved[0, 2], moved[1, 2], moved[2, 2])
        # node (a, c, e) got weight (mass, p_node), p_node = at_origin + per_x a + per_y c + per_z e.
        # The sums are scatter_plane's adjoint's over three planes, written in this loop: the same
        # nine-node sums called as a function of several results took the kernel from 168 to 254
        # registers (nvcc for sm_90).
        adj_wx = wp.vec3(0.0)
        adj_wy = wp.vec3(0.0)
        adj_wz = wp.vec3(0.0)
        adj_mass = float(0.0)
        adj_origin = wp.vec3(0.0)  # sum of weight gp
        adj_x_col = wp.vec3(0.0)  # sum of a weight gp, per_x's adjoint; likewise along y and z
        adj_y_col = wp.vec3(0.0)
        adj_z_col = wp.vec3(0.0)
        for a in range(3):
            for c in range(3):
                for e in range(3):
                    node = offset + node_index(base[0] + a, base[1] + c, base[2] + e, dims)
                    gm = adj_grid_m[node]
                    gp = adj_grid_p[node]
                    weight = wx[a] * wy[c] * wz[e]
                    p_node = at_origin + per_x * float(a) + per_y * float(c) + per_z * float(e)
                    d_weight = gm * mass + wp.dot(gp, p_node)
                    adj_wx[a] = adj_wx[a] + d_weight * wy[c] * wz[e]
                    adj_wy[c] = adj_wy[c] + d_weight * wx[a] * wz[e]
                    adj_wz[e] = adj_wz[e] + d_weight * wx[a] * wy[c]
                    adj_mass += weight * gm
                    weighted = gp * weight
                    adj_origin += weighted
                    adj_x_col += weighted * float(a)
                    adj_y_col += weighted * float(c)
                    adj_z_col += weighted * float(e)
        # at_origin = v mass - moved fx
        adj_moved = wp.mat33(adj_x_col[0], adj_y_col[0], adj_z_col[0], adj_x_col[1], adj_y_col[1], adj_z_col[1],
                             adj_x_col[2], adj_y_col[2], adj_z_col[2]) - wp.outer(adj_origin, fx)
        adj_fx = wp.vec3(wp.dot(adj_wx, bspline_slopes(fx[0])), wp.dot(adj_wy, bspline_slopes(fx[1])),
                         wp.dot(adj_wz, bspline_slopes(fx[2]))) - wp.transpose(moved) * adj_origin
        adj_src_x[i] = adj_src_x[i] + adj_fx * inv_dx
        adj_src_v[i] = adj_src_v[i] + adj_origin * mass
        adj_affine = adj_moved * dx
        adj_tau = adj_affine * (stress_scale * vol)
        adj_mass += wp.dot(adj_origin, v_i) + wp.ddot(adj_affine, C_i)
        add_material_param(adj_density, q, i, adj_mass * vol)
        if adj_volume.shape[0] > 0:
            adj_volume[i] = adj_volume[i] + wp.ddot(adj_affine, tau) * stress_scale + adj_mass * rho
        if adj_grid_tau.shape[0] > 0:
            adj_grid_tau[i] = adj_grid_tau[i] + adj_tau
        # the material update's adjoint, from the state read again: b' = return_mapping(f b f^T), f = I + h C
        b_i = src_b[i]
        E_q = param(E, q, i)
        nu_q = param(nu, q, i)
        f = wp.identity(n=3, dtype=float) + C_i * h
        b_trial = f * b_i * wp.transpose(f)
        b_new = return_mapping(fam, b_trial, E_q, nu_q, param(yield_stress, q, i), param(friction_angle, q, i))
        adj_b_new, adj_C, adj_mu, adj_lambda, adj_bulk_q, adj_viscosity_q = kirchhoff_stress_adjoint(
            fam, b_new, C_i, E_q, nu_q, param(bulk_modulus, q, i), param(viscosity, q, i), adj_tau)
        adj_trial, adj_mu_r, adj_lambda_r, adj_yield_q, adj_angle_q = return_mapping_adjoint(
            fam, b_trial, E_q, nu_q, param(yield_stress, q, i), param(friction_angle, q, i), adj_b_new + adj_dst_b[i])
        adj_E_q, adj_nu_q = lame_adjoint(E_q, nu_q, adj_mu + adj_mu_r, adj_lambda + adj_lambda_r)
        add_material_param(adj_E, q, i, adj_E_q)
        add_material_param(adj_nu, q, i, adj_nu_q)
        add_material_param(adj_yield_stress, q, i, adj_yield_q)
        add_material_param(adj_friction_angle, q, i, adj_angle_q)
        add_material_param(adj_bulk_modulus, q, i, adj_bulk_q)
        add_material_param(adj_viscosity, q, i, adj_viscosity_q)
        # b_trial = f b f^T
        adj_f = adj_trial * (f * wp.transpose(b_i)) + wp.transpose(adj_trial) * (f * b_i)
        adj_src_b[i] = adj_src_b[i] + wp.transpose(f) * adj_trial * f
        adj_src_C[i] = adj_src_C[i] + adj_affine * mass + adj_C + adj_f * h

    return wp.Kernel(p2g_adjoint, key=key, module=module, options={"enable_backward": False})


@wp.kernel(enable_backward=False)
def check_state(
    state_x: wp.array(dtype=wp.vec3),
    state_v: wp.array(dtype=wp.vec3),
    state_b: wp.array(dtype=wp.mat33),
    obj: wp.array(dtype=int),
    n_particles: int,
    n_objects: int,
    lo: wp.vec3,
    hi: wp.vec3,
    stats: wp.array(dtype=float),
):
    """Per (batch, object): [max speed, non-finite count, outside-domain count, min det b] (no adjoint)."""
    i = wp.tid()
    batch = i // n_particles
    k = obj[i - batch * n_particles]
    row = 4 * (batch * n_objects + k)
    speed = wp.length(state_v[i])
    det = wp.determinant(state_b[i])
    finite = wp.isfinite(state_x[i]) and wp.isfinite(state_v[i]) and wp.isfinite(det)
    if finite:
        wp.atomic_max(stats, row, speed)
        wp.atomic_min(stats, row + 3, det)
        p = state_x[i]
        if p[0] < lo[0] or p[1] < lo[1] or p[2] < lo[2] or p[0] > hi[0] or p[1] > hi[1] or p[2] > hi[2]:
            wp.atomic_add(stats, row + 2, 1.0)
    else:
        wp.atomic_add(stats, row + 1, 1.0)
