"""Warp-aggregated grid scatter: the lanes of a CUDA warp that add to one grid node add once.

P2G adds every particle's mass and momentum to the 27 nodes of its stencil with float atomics,
and so does G2P's adjoint (``kernels.g2p_adjoint``) with the particles' velocity adjoints.
Particles next to each other in memory mostly share their stencil (the lattices of
``sim.sampling`` and of lifting put two particles per cell along their fastest axis; particles
sorted by cell put all of a cell's together), so a warp's 32 lanes hit far fewer than 32
distinct nodes, and atomics to one address are serialised in the L2 cache: on an H100 P2G was
bound by them (Nsight Compute: 64 % of the L2's throughput, 4 % of DRAM's, 649 of a substep's
755 us at 1M particles).

Here the lanes of a warp with the same key (the field node of their stencil's first corner, so
that equal keys mean equal stencils) that sit next to each other form a run. ``add`` sums a
run's values with a segmented scan over warp shuffles (Hillis-Steele, log2 of the longest run
steps), and its last lane does the one add (one vector reduction where the target is the
first three floats of 16-byte slots and the device has it). ``scatter``, P2G's, takes a plane
of nine nodes at a time: the lanes stage their nine values in shared memory, and the lanes of
each run sum them node by node, each lane a node, and add each sum once (one vector reduction
for the mass and momentum where the device has it). ``clear_node`` is G2P's 16-byte store
that clears a node's slot. No function here has an adjoint: P2G's adjoint reads its
stencil's nodes in a function of its own (``kernels.scatter_plane``).

On the CPU (no warps; the threads of a launch run in order) every function is the plain atomic
add it replaces, so CPU results are unchanged to the bit. Runs are recomputed in every
call from the lanes that are active there, so a warp that diverged between calls only makes
shorter runs. On CUDA the summation order differs from one atomic per lane (float sums, the
same to rounding), as the order of atomics already did from run to run.
"""

from __future__ import annotations

import warp as wp

_LANES = """
    const unsigned mask = __activemask();
    const int lane = threadIdx.x & 31;
"""

_RUN_START = """
#if defined(__CUDA_ARCH__)
""" + _LANES + """
    const int before = __shfl_up_sync(mask, key, 1);
    const bool head = lane == 0 || !((mask >> (lane - 1)) & 1u) || before != key;
    const unsigned heads = (__ballot_sync(mask, head) | ~mask) & (0xffffffffu >> (31 - lane));
    return 31 - __clz(heads);
#else
    return 0;
#endif
"""

# The run of this lane in this call: from max(run, the lane after the last inactive one below),
# to the last lane whose start is the same. ``tail``: this lane ends its run.
_RUN = _LANES + """
    const unsigned idle = lane ? (~mask & ((1u << lane) - 1u)) : 0u;
    const int start = max(run, idle ? 32 - __clz(idle) : 0);
    const int next = __shfl_down_sync(mask, start, 1);
    const bool tail = lane == 31 || !((mask >> (lane + 1)) & 1u) || next != start;
"""


def _scan(*names: str) -> str:
    """Segmented inclusive sums of the float variables ``names`` over this lane's run."""
    ups = "".join(f"            const float up_{k} = __shfl_up_sync(mask, {n}, d);\n"
                  for k, n in enumerate(names))
    adds = "".join(f"                {n} += up_{k};\n" for k, n in enumerate(names))
    return f"""
    for (int d = 1; d < 32; d <<= 1) {{
        if (!__any_sync(mask, lane - start >= d)) break;
{ups}        if (lane - start >= d) {{
{adds}        }}
    }}
"""


def _red_v4(slot: str, x: str, y: str, z: str, w: str) -> str:
    """CUDA that adds the floats x, y, z, w to the aligned 16-byte slot at ``slot`` (a ``float*``) in one request."""
    return f"""
            asm volatile("red.global.add.v4.f32 [%0], {{%1, %2, %3, %4}};"
                         :: "l"(__cvta_generic_to_global({slot})), "f"({x}), "f"({y}), "f"({z}), "f"({w})
                         : "memory");
"""


# Whether grid_m and grid_p are the simulator's one aligned 16-byte slot a node, momentum then mass
_SLOTS = """(char*)grid_m.data == (char*)grid_p.data + 12 && grid_m.strides[0] == 16 \
        && grid_p.strides[0] == 16 && ((size_t)grid_p.data & 15) == 0"""

_SCATTER = """
#if defined(__CUDA_ARCH__)
    // Node j of the plane is staged in this lane's row of shared memory; the ninth call sums
    // the rows of each run node by node, a lane of the run a node, and adds each sum once.
    __shared__ float4 staged[256 * 9];
    if (blockDim.x > 256) {  // Warp 1.4 launches blocks of 256 threads; any more add lane by lane
        wp::atomic_add(grid_m, node, m);
        wp::atomic_add(grid_p, node, p);
        return;
    }
    staged[threadIdx.x * 9 + j] = make_float4(p[0], p[1], p[2], m);
    if (j == 8) {
""" + _RUN + """
        const unsigned tails = __ballot_sync(mask, tail);
        const int length = __ffs(tails & (0xffffffffu << lane)) - start;  // lanes start to its tail
        const int first = threadIdx.x - lane + start;
        __syncwarp(mask);
        for (int k = lane - start; k < 9; k += length) {
            float4 sum = staged[first * 9 + k];
            for (int q = 1; q < length; ++q) {
                const float4 row = staged[(first + q) * 9 + k];
                sum.x += row.x; sum.y += row.y; sum.z += row.z; sum.w += row.w;
            }
            const int target = node - (2 - k / 3) * dims_z - (2 - k % 3);
#if __CUDA_ARCH__ >= 900
            if (""" + _SLOTS + """) {
""" + _red_v4("(float*)((char*)grid_p.data + (size_t)target * 16)", "sum.x", "sum.y", "sum.z", "sum.w") + """
            } else
#endif
            {
                wp::atomic_add(grid_m, target, sum.w);
                wp::atomic_add(grid_p, target, wp::vec3(sum.x, sum.y, sum.z));
            }
        }
        __syncwarp(mask);  // the rows are read before the next plane's first call writes them
    }
#else
    wp::atomic_add(grid_m, node, m);
    wp::atomic_add(grid_p, node, p);
#endif
"""

_ADD = """
#if defined(__CUDA_ARCH__)
""" + _RUN + """
    float sum_x = value[0], sum_y = value[1], sum_z = value[2];
""" + _scan("sum_x", "sum_y", "sum_z") + """
    if (tail) {
#if __CUDA_ARCH__ >= 900
        if (target.strides[0] == 16 && ((size_t)target.data & 15) == 0) {  // the first three floats of slots
""" + _red_v4("(float*)((char*)target.data + (size_t)node * 16)", "sum_x", "sum_y", "sum_z", "0.0f") + """
        } else
#endif
        wp::atomic_add(target, node, wp::vec3(sum_x, sum_y, sum_z));
    }
#else
    wp::atomic_add(target, node, value);
#endif
"""


@wp.func_native(_RUN_START)
def run_start(key: int) -> int:
    """The first lane of this lane's run of equal ``key`` in its warp (0 on the CPU)."""
    ...


@wp.func_native(_SCATTER)
def scatter(grid_m: wp.array(dtype=float), grid_p: wp.array(dtype=wp.vec3), node: int, j: int, dims_z: int,
            run: int, m: float, p: wp.vec3):
    """grid_m[node] += m and grid_p[node] += p for node ``j`` = 3 c + e of a plane of a stencil.

    A lane calls it for j = 0, ..., 8 in order, from nodes whose index steps by ``dims_z`` with
    c and by one with e (``kernels.node_index``). The first eight calls stage their values in
    shared memory; the ninth adds the nine sums of each run of lanes (``run_start``), a lane of
    the run a node, instead of each lane adding each of its nodes (P2G's scatter on an H200:
    22.1 against 28.6 us a substep for 32 rows of a 2,744-particle block; docs/simulator.md).
    Where each node's mass follows its momentum in one aligned 16-byte slot (the simulator's
    grids, ``simulator._momentum_and_mass``) and the code is built for compute capability 9.0
    or later, a sum is added with one vector reduction (``red.global.add.v4.f32``), one request
    to the L2 instead of two. No adjoint: P2G's adjoint gathers its nodes' adjoints itself
    (``kernels.scatter_plane``).
    """
    ...


@wp.func_native(_ADD)
def add(target: wp.array(dtype=wp.vec3), node: int, run: int, value: wp.vec3):
    """target[node] += value, once per run of lanes (``run_start``); not differentiable.

    Where ``target`` is the first three floats of aligned 16-byte slots (the velocity gradients
    of the simulator's grids on a device of compute capability 9.0 or later,
    ``simulator._slot_vectors``), a run adds with one vector reduction, its fourth float zero,
    instead of three atomics (G2P's adjoint; on an H200 a million particles' backward in
    ``sim_throughput.py`` took about 0.88 times as long, docs/simulator.md).
    """
    ...


@wp.func_native("""
#if defined(__CUDA_ARCH__)
    if (""" + _SLOTS + """) {
        *(float4*)((char*)grid_p.data + (size_t)node * 16) = make_float4(0.0f, 0.0f, 0.0f, 0.0f);
        return;
    }
#endif
    wp::index(grid_m, node) = 0.0f;
    wp::index(grid_p, node) = wp::vec3(0.0f);
""")
def clear_node(grid_m: wp.array(dtype=float), grid_p: wp.array(dtype=wp.vec3), node: int):
    """grid_m[node] = 0 and grid_p[node] = 0: one 16-byte store where they share a slot (G2P)."""
    ...
