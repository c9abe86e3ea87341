"""Host-side orchestration of the Warp rasterizer: scratch buffers, binning cache, CPU threading.

``rasterize_forward`` and ``rasterize_backward`` take and fill ``wp.array`` buffers (as handed over
by ``wp.jax_callable``) and launch, in order:

forward:  validate -> project -> depth sort -> binning -> splat records (tile kernels) -> composite
          binning on the CPU: gather in depth order -> count hits per (depth chunk, tile) ->
          scan (one host read of the total) -> scatter front to back into the tile lists;
          on CUDA: count -> scan -> write (tile | depth rank) keys -> radix sort -> tile ranges
backward: composite adjoint -> projection adjoint -> viewmat reduction
pose-only backward (:func:`rasterize_backward_pose`): composite adjoint of the depth, conic and
          mean2d cotangents only -> viewmat part of the projection adjoint, reduced in fixed chunks

Scratch buffers live in a per-device :class:`Workspace` and grow geometrically, so steady-state
calls allocate nothing. The sorted intersection list (and the tile kernels' splat records) of a
forward call is kept in one of a small ring of slots and found again by the backward through a
``(slot, generation)`` handle; when the slot has been reused in between (many renders before one
backward), the backward re-bins from the saved projection, which gives the identical order.

On the CPU a Warp launch runs on one thread; every per-Gaussian pass and the compositing are
therefore split into chunks (tile rows for the compositing) that worker threads take round-robin
(:mod:`.parallel`; Warp releases the GIL inside a launch). Each worker has its own gradient
accumulators, summed at the end in a fixed order, so results do not depend on the thread count.
"""
from __future__ import annotations

import threading
from dataclasses import dataclass, field

import numpy as np
import warp as wp

# Warp's automatic adjoints are never used: every backward here is written by hand.
wp.set_module_options({"enable_backward": False})

from .binning import (
    count_tiles_kernel,
    count_tiles_ranked_kernel,
    depth_keys_kernel,
    gather_sorted_kernel,
    depth_rank_kernel,
    scatter_ids_kernel,
    tile_cursors_kernel,
    tile_ranges_kernel,
    write_keys_kernel,
)
from .composite import (
    TILE_LANES,
    bwd_scratch_fields,
    POSE_NG,
    composite_kernels,
    composite_pose_kernels,
    composite_tile_kernels,
    composite_top_id,
    splat_record_size,
    splat_records_kernel,
)
from .config import resolve_composite
from .parallel import launch_split, n_threads_for, run_bands
from .projection import VIEW_CHUNK, project_bwd_kernel, project_bwd_viewmat_kernel, project_fwd_kernel
from .validate import FLAG_MESSAGES, N_FLAGS, InputValueError, validate_camera_kernel, validate_gaussians_kernel

TILE_SIZE = 16
N_SLOTS = 8
#: accumulation slots for the viewmat gradient (spreads CUDA atomics)
VIEWMAT_SLOTS = 64
#: accumulator groups of the pose-only backward on the CPU: tile row r adds into group r % 8. A
#: fixed number (not one per thread) keeps every sum's order, hence the result, independent of the
#: thread count; 8 groups still share out the rows among up to 8 threads.
POSE_GROUPS = 8


@wp.kernel
def _sum_rows_kernel(src: wp.array2d(dtype=float), dst: wp.array(dtype=float)):
    k = wp.tid()
    s = float(0.0)
    for r in range(src.shape[0]):
        s += src[r, k]
    dst[k] = s


@wp.kernel
def _stash_total_kernel(offsets: wp.array(dtype=wp.int32), n: int, flags: wp.array(dtype=wp.int32)):
    flags[N_FLAGS] = offsets[n - 1]


@wp.kernel
def _add_float_kernel(src: wp.array(dtype=float), dst: wp.array(dtype=float)):
    i = wp.tid()
    dst[i] = dst[i] + src[i]


@wp.kernel
def _add_vec2_kernel(src: wp.array(dtype=wp.vec2), dst: wp.array(dtype=wp.vec2)):
    i = wp.tid()
    dst[i] = dst[i] + src[i]


@wp.kernel
def _add_vec3_kernel(src: wp.array(dtype=wp.vec3), dst: wp.array(dtype=wp.vec3)):
    i = wp.tid()
    dst[i] = dst[i] + src[i]


@wp.kernel
def _add_flat_kernel(src: wp.array2d(dtype=float), dst: wp.array2d(dtype=float)):
    i, k = wp.tid()
    dst[i, k] = dst[i, k] + src[i, k]


class Workspace:
    """Named scratch buffers on one device that only ever grow (by 1.5x), never shrink."""

    def __init__(self, device):
        self.device = device
        self._bufs: dict[str, wp.array] = {}
        self.lock = threading.RLock()

    def get(self, name: str, n: int, dtype, zero: bool = False) -> wp.array:
        buf = self._bufs.get(name)
        if buf is None or buf.shape[0] < n or buf.dtype != dtype:
            cap = max(n, int(1.5 * buf.shape[0]) if buf is not None else n, 16)
            buf = wp.empty(cap, dtype=dtype, device=self.device)
            self._bufs[name] = buf
        view = buf[:n] if n > 0 else buf[:0]
        if zero and n > 0:
            view.zero_()
        return view

    def get2d(self, name: str, rows: int, cols: int, dtype, zero: bool = False) -> wp.array:
        flat = self.get(name, rows * cols, dtype)
        view = wp.array(ptr=flat.ptr, shape=(rows, cols), dtype=dtype, device=self.device, copy=False) \
            if rows * cols > 0 else wp.empty((rows, cols), dtype=dtype, device=self.device)
        if zero and rows * cols > 0:
            view.zero_()
        return view


@dataclass
class BinState:
    """Binning of one forward call: the sorted intersection list and per-tile ranges."""

    generation: int = -1
    n_isect: int = 0
    ranges: wp.array | None = None  # (num_tiles, 2) int32
    ids: wp.array | None = None  # (n_isect,) int32, Gaussian index per intersection
    rec: wp.array | None = None  # the tile kernels' splat records of the call (None: pixel kernels)
    ws: Workspace | None = None


@dataclass
class _DeviceState:
    ws: Workspace
    slots: list[BinState] = field(default_factory=list)
    next_slot: int = 0
    generation: int = 0


#: Module-level cache: one :class:`_DeviceState` (scratch workspace + ring of binning slots) per
#: device name, created on first use and kept for the life of the process; its buffers only grow.
_STATES: dict[str, _DeviceState] = {}
_STATES_LOCK = threading.Lock()


def _device_state(device) -> _DeviceState:
    key = str(device)
    with _STATES_LOCK:
        st = _STATES.get(key)
        if st is None:
            st = _DeviceState(ws=Workspace(device))
            st.slots = [BinState(ws=Workspace(device)) for _ in range(N_SLOTS)]
            _STATES[key] = st
        return st


def grid_dims(width: int, height: int, tile: int = TILE_SIZE) -> tuple[int, int]:
    return (width + tile - 1) // tile, (height + tile - 1) // tile


def project(means, quats, scales, opacities, viewmat, K, width, height, near, far, eps2d,
            means2d, conics, depths, radii, threads: int | None = None) -> None:
    """Launch the projection kernel (all arguments are Warp arrays / scalars)."""
    n = means.shape[0]
    if n == 0:
        return
    pre = [means, quats, scales, opacities, viewmat, K, width, height, near, far, eps2d]
    launch_split(project_fwd_kernel, n, lambda i0, _w: pre + [i0], [means2d, conics, depths, radii], means.device,
                 threads)


def bin_gaussians(ws: Workspace, means2d, conics, opacities, depths, radii, width: int, height: int,
                  tile: int = TILE_SIZE, flags: wp.array | None = None,
                  threads: int | None = None) -> tuple[wp.array, wp.array, int]:
    """Build the depth-ordered per-tile intersection lists.

    Returns ``(ranges (num_tiles, 2) int32, ids (n_isect,) int32, n_isect)``; the buffers belong
    to ``ws`` and stay valid until its next ``bin_gaussians`` call. When ``flags`` (N_FLAGS + 1,)
    is given, validation flags are read back in the same host transfer as the count and a
    ``ValueError`` naming the offending argument is raised.
    """
    device = means2d.device
    n = means2d.shape[0]
    tiles_x, tiles_y = grid_dims(width, height, tile)
    n_tiles = tiles_x * tiles_y
    ranges = ws.get2d("ranges", n_tiles, 2, wp.int32, zero=True)
    if n == 0:
        if flags is not None:
            _raise_flags(flags.numpy())
        return ranges, ws.get("ids", 0, wp.int32), 0
    dkeys = ws.get("dkeys", 2 * n, wp.float32)
    order = ws.get("order", 2 * n, wp.int32)
    wp.launch(depth_keys_kernel, dim=n, inputs=[depths, radii], outputs=[dkeys, order], device=device)
    wp.utils.radix_sort_pairs(dkeys, order, n)
    binner = _bin_by_counting if wp.get_device(device).is_cpu else _bin_by_key_sort
    return binner(ws, order, means2d, conics, opacities, radii, width, height, tile, ranges, flags, threads)


def _bin_by_key_sort(ws: Workspace, order, means2d, conics, opacities, radii, width: int, height: int, tile: int,
                     ranges, flags, threads: int | None) -> tuple[wp.array, wp.array, int]:
    """Binning for CUDA: keys ``tile << rank_bits | depth rank`` written in parallel, then one
    stable radix sort (it also runs on the CPU, where :func:`_bin_by_counting` is faster)."""
    device = means2d.device
    n = means2d.shape[0]
    tiles_x, tiles_y = grid_dims(width, height, tile)
    n_tiles = tiles_x * tiles_y
    rank = ws.get("rank", n, wp.int32)
    wp.launch(depth_rank_kernel, dim=n, inputs=[order], outputs=[rank], device=device)
    counts = ws.get("counts", n, wp.int32)
    masks = ws.get("masks", n, wp.int32)
    offsets = ws.get("offsets", n, wp.int32)
    grid = [tile, tiles_x, tiles_y, width, height]
    gauss = [means2d, conics, opacities, radii]
    launch_split(count_tiles_kernel, n, lambda j0, _w: gauss + grid + [j0], [counts, masks], device, threads)
    wp.utils.array_scan(counts, offsets, inclusive=True)
    if flags is not None:
        wp.launch(_stash_total_kernel, dim=1, inputs=[offsets, n, flags], device=device)
        host = flags.numpy()  # the single host round trip of a forward
        _raise_flags(host)
        n_isect = int(host[N_FLAGS])
    else:
        n_isect = int(offsets[n - 1:n].numpy()[0])
    ids = ws.get("ids", 2 * max(n_isect, 1), wp.int32)
    if n_isect == 0:
        return ranges, ids[:0], 0
    keys = ws.get("keys", 2 * n_isect, wp.int64)
    rank_bits = max(1, int(n - 1).bit_length())
    launch_split(write_keys_kernel, n, lambda j0, _w: [rank] + gauss + [offsets, masks] + grid + [j0, rank_bits],
                 [keys, ids], device, threads)
    end_bit = rank_bits + max(1, int(n_tiles - 1).bit_length())
    wp.utils.radix_sort_pairs(keys, ids, n_isect, end_bit=end_bit)
    wp.launch(tile_ranges_kernel, dim=n_isect, inputs=[keys, n_isect, rank_bits], outputs=[ranges], device=device)
    return ranges, ids[:n_isect], n_isect


#: depth-rank chunks per worker thread of the CPU binning (the near chunks hit more tiles)
BIN_CHUNKS_PER_THREAD = 4
MAX_BIN_CHUNKS = 64


def _bin_by_counting(ws: Workspace, order, means2d, conics, opacities, radii, width: int, height: int, tile: int,
                     ranges, flags, threads: int | None) -> tuple[wp.array, wp.array, int]:
    """CPU binning without a key sort: count hits per (chunk of depth ranks, tile), scan, and
    scatter each chunk's Gaussians front to back into the tile lists (see :mod:`.binning`).
    The chunks run on the worker threads; the lists do not depend on how many there are."""
    device = means2d.device
    n = means2d.shape[0]
    tiles_x, tiles_y = grid_dims(width, height, tile)
    n_tiles = tiles_x * tiles_y
    n_threads = n_threads_for(device, threads) if n >= 4096 else 1
    # capped: the scan over (tile, chunk) is serial
    n_chunks = min(n_threads * BIN_CHUNKS_PER_THREAD, MAX_BIN_CHUNKS) if n_threads > 1 else 1
    bounds = [(n * c // n_chunks, n * (c + 1) // n_chunks) for c in range(n_chunks)]
    bands = [bd for bd in bounds if bd[1] > bd[0]]
    chunk_of = {bd: c for c, bd in enumerate(bands)}
    n_chunks = len(bands)
    hist = ws.get2d("tile_hist", n_chunks, n_tiles, wp.int32, zero=True)
    masks = ws.get("masks", n, wp.int32)
    grid = [tile, tiles_x, tiles_y, width, height]
    gauss = [ws.get("s_means2d", n, wp.vec2), ws.get("s_conics", n, wp.vec3), ws.get("s_opacities", n, wp.float32),
             ws.get("s_radii", n, wp.vec2i)]

    def count(_w, j0, j1):
        wp.launch(gather_sorted_kernel, dim=j1 - j0, inputs=[order, means2d, conics, opacities, radii, j0],
                  outputs=gauss, device=device)
        wp.launch(count_tiles_ranked_kernel, dim=j1 - j0, inputs=gauss + grid + [j0, chunk_of[(j0, j1)]],
                  outputs=[masks, hist], device=device)

    gather_sorted_kernel.module.load(wp.get_device(device))
    run_bands(bands, n_threads, count, count_tiles_ranked_kernel, device)
    total = flags if flags is not None else ws.get("isect_total", 1, wp.int32)
    wp.launch(tile_cursors_kernel, dim=1, inputs=[hist, n_tiles, n_chunks, N_FLAGS if flags is not None else 0],
              outputs=[ranges, total], device=device)
    host = total.numpy()  # the single host round trip of a forward
    if flags is not None:
        _raise_flags(host)
        n_isect = int(host[N_FLAGS])
    else:
        n_isect = int(host[0])
    ids = ws.get("ids", max(n_isect, 1), wp.int32)
    if n_isect == 0:
        return ranges, ids[:0], 0

    def scatter(_w, j0, j1):
        wp.launch(scatter_ids_kernel, dim=j1 - j0,
                  inputs=[order] + gauss + [masks] + grid + [j0, chunk_of[(j0, j1)], hist], outputs=[ids],
                  device=device)

    run_bands(bands, n_threads, scatter, scatter_ids_kernel, device)
    return ranges, ids[:n_isect], n_isect


def _flat_floats(ws: Workspace, colors, n: int, C: int) -> wp.array:
    """``colors`` (n,) vecC seen as n * C contiguous floats (a one-element scratch when n = 0)."""
    if n == 0:
        return ws.get("flat_empty", 1, wp.float32)
    return wp.array(ptr=colors.ptr, shape=(n * C,), dtype=wp.float32, device=colors.device, copy=False)


def splat_records(ws: Workspace, means2d, conics, opacities, depths, colors, radii,
                  threads: int | None = None) -> wp.array:
    """The tile forward's per-Gaussian records (:func:`.composite.splat_records_kernel`), built
    in parallel chunks into ``ws``'s buffer "splat_rec" (n * record size floats)."""
    n = means2d.shape[0]
    C = colors.dtype._length_ if hasattr(colors.dtype, "_length_") else 1
    RS = splat_record_size(C)
    rec = ws.get("splat_rec", max(1, n * RS), wp.float32)
    if n > 0:
        colf = _flat_floats(ws, colors, n, C)
        launch_split(splat_records_kernel, n,
                     lambda i0, _w: [means2d, conics, opacities, depths, colf, radii, C, RS, i0], [rec],
                     means2d.device, threads)
    return rec


def _raise_flags(host_flags: np.ndarray) -> None:
    for k in range(N_FLAGS):
        if host_flags[k]:
            raise InputValueError(FLAG_MESSAGES[k])


def _row_bands(width: int, height: int, tile: int, n_threads: int) -> list[tuple[int, int]]:
    """Pixel ranges of tile-row bands, several per thread so that uneven rows balance out."""
    tiles_y = (height + tile - 1) // tile
    n_bands = tiles_y if n_threads > 1 else 1
    bands = []
    for b in range(n_bands):
        r0 = (b * tiles_y // n_bands) * tile
        r1 = min(height, ((b + 1) * tiles_y // n_bands) * tile)
        if r1 > r0:
            bands.append((r0 * width, r1 * width))
    return bands


def _tile_bands(n_tiles: int, tiles_x: int, n_threads: int) -> list[tuple[int, int]]:
    """Tile-index ranges, one tile row each when threaded (rows differ a lot in cost)."""
    if n_threads <= 1:
        return [(0, n_tiles)]
    return [(r, min(n_tiles, r + tiles_x)) for r in range(0, n_tiles, tiles_x)]


def rasterize_forward(means, quats, scales, opacities, colors, viewmat, K, width: int, height: int,
                      near: float, far: float, eps2d: float,
                      out_color, out_depth, out_T, out_last, means2d, conics, depths, radii,
                      n_isect_out, handle_out, tile: int = TILE_SIZE, validate: bool = True,
                      composite: str | None = None, threads: int | None = None) -> BinState:
    """Full forward pass into the given output arrays; returns the slot that holds the binning.

    ``composite``: "tile" or "pixel" compositing kernel, ``threads``: CPU worker threads; None
    takes the defaults of :mod:`splatsearch.kernels.config`.

    Shapes: means (N,) vec3, quats (N,) vec4 wxyz, scales (N,) vec3, opacities (N,), colors (N,)
    vecC, viewmat (1,) mat44, K (1,) mat33; images are flat (H*W,) in row-major pixel order.
    ``n_isect_out`` (1,) int32 and ``handle_out`` (2,) int32 receive the intersection count and
    the (slot, generation) handle for :func:`rasterize_backward`.
    """
    device = means.device
    st = _device_state(device)
    with st.ws.lock:
        C = colors.dtype._length_ if hasattr(colors.dtype, "_length_") else 1
        n = means.shape[0]
        flags = st.ws.get("flags", N_FLAGS + 1, wp.int32, zero=True)
        if validate:
            if n > 0:
                colors2d = wp.array(ptr=colors.ptr, shape=(n, C), dtype=wp.float32, device=device, copy=False)
                launch_split(validate_gaussians_kernel, n,
                             lambda i0, _w: [means, quats, scales, opacities, colors2d, i0], [flags], device, threads)
            wp.launch(validate_camera_kernel, dim=1, inputs=[viewmat, K], outputs=[flags], device=device)
        project(means, quats, scales, opacities, viewmat, K, width, height, near, far, eps2d,
                means2d, conics, depths, radii, threads)
        slot_idx = st.next_slot
        st.next_slot = (st.next_slot + 1) % N_SLOTS
        st.generation += 1
        slot = st.slots[slot_idx]
        slot.generation = -1
        ranges, ids, n_isect = bin_gaussians(slot.ws, means2d, conics, opacities, depths, radii,
                                             width, height, tile, flags=flags, threads=threads)
        slot.generation, slot.ranges, slot.ids, slot.n_isect, slot.rec = st.generation, ranges, ids, n_isect, None
        tiles_x, tiles_y = grid_dims(width, height, tile)
        n_threads = n_threads_for(device, threads)
        if resolve_composite(composite, device) == "tile":
            if tile != TILE_LANES:
                raise ValueError(f"the tile compositing kernels need tile={TILE_LANES}, got {tile}")
            fwd, _ = composite_tile_kernels(C)
            n_tiles = tiles_x * tiles_y
            sT = st.ws.get("tile_T", n_tiles * 256, wp.float32)
            sD = st.ws.get("tile_D", n_tiles * 256, wp.float32)
            sL = st.ws.get("tile_L", n_tiles * 256, wp.int32)
            sC = st.ws.get("tile_C", n_tiles * 256 * C, wp.float32)
            live = st.ws.get("live", n_tiles * 16, wp.vec2i)
            rec = splat_records(slot.ws, means2d, conics, opacities, depths, colors, radii, threads)
            slot.rec = rec  # the backward reuses them while the slot holds this call

            def launch(_w, t0, t1):
                wp.launch(fwd, dim=t1 - t0,
                          inputs=[ranges, ids, rec, width, height, tiles_x, t0, sT, sD, sL, sC, live],
                          outputs=[out_color, out_depth, out_T, out_last], device=device)

            bands = _tile_bands(tiles_x * tiles_y, tiles_x, n_threads)
        else:
            fwd, _, _ = composite_kernels(C)

            def launch(_w, p0, p1):
                wp.launch(fwd, dim=p1 - p0,
                          inputs=[ranges, ids, means2d, conics, opacities, colors, depths, width, tile, tiles_x, p0],
                          outputs=[out_color, out_depth, out_T, out_last], device=device)

            bands = _row_bands(width, height, tile, n_threads)
        run_bands(bands, n_threads, launch, fwd, device)
        n_isect_out.fill_(n_isect)
        handle_np = np.array([slot_idx, st.generation], dtype=np.int32)
        wp.copy(handle_out, wp.array(handle_np, dtype=wp.int32, device=device))
        return slot


def _live_slot(device, handle: tuple[int, int]) -> BinState | None:
    """The ring slot that still holds the forward call of ``handle``, else None."""
    st = _device_state(device)
    slot_idx, gen = handle
    if 0 <= slot_idx < N_SLOTS:
        slot = st.slots[slot_idx]
        if slot.generation == gen and slot.ranges is not None:
            return slot
    return None


def lookup_binning(device, handle: tuple[int, int], means2d, conics, opacities, depths, radii,
                   width: int, height: int, tile: int = TILE_SIZE,
                   threads: int | None = None) -> tuple[wp.array, wp.array, int]:
    """Binning for ``handle`` from the slot ring, or recomputed when the slot was reused."""
    slot = _live_slot(device, handle)
    if slot is not None:
        return slot.ranges, slot.ids, slot.n_isect
    return bin_gaussians(_device_state(device).ws, means2d, conics, opacities, depths, radii, width, height, tile,
                         threads=threads)


def rasterize_backward(means, quats, scales, opacities, colors, viewmat, K, width: int, height: int,
                       eps2d: float, means2d, conics, depths, radii, out_T, out_last, handle,
                       v_color, v_depth, v_alpha,
                       v_means, v_quats, v_scales, v_opacities, v_colors, v_viewmat,
                       tile: int = TILE_SIZE, composite: str | None = None, threads: int | None = None) -> None:
    """Hand-written adjoint of :func:`rasterize_forward` (``composite`` and ``threads`` as there).

    ``v_color`` (H*W,) vecC, ``v_depth`` and ``v_alpha`` (H*W,) are the cotangents of the
    composited colour, depth (D) and alpha = 1 - T. Writes v_means (N,) vec3, v_quats (N,) vec4,
    v_scales (N,) vec3, v_opacities (N,), v_colors (N,) vecC and v_viewmat (16,) row-major.
    ``handle`` is the host tuple (slot, generation) returned through ``handle_out``.
    """
    device = means.device
    st = _device_state(device)
    n = means.shape[0]
    C = colors.dtype._length_ if hasattr(colors.dtype, "_length_") else 1
    with st.ws.lock:
        v_viewmat.zero_()
        v_opacities.zero_()
        v_colors.zero_()
        if n == 0:
            return
        ranges, ids, _ = lookup_binning(device, handle, means2d, conics, opacities, depths, radii,
                                        width, height, tile, threads)
        tiles_x, tiles_y = grid_dims(width, height, tile)
        n_threads = n_threads_for(device, threads)
        variant = resolve_composite(composite, device)
        ws = st.ws
        accs = []
        for w in range(n_threads):
            if w == 0:
                acc = (ws.get("v_means2d", n, wp.vec2, zero=True), ws.get("v_conics", n, wp.vec3, zero=True),
                       v_opacities, v_colors, ws.get("v_depths", n, wp.float32, zero=True))
            else:
                acc = (ws.get(f"v_means2d{w}", n, wp.vec2, zero=True), ws.get(f"v_conics{w}", n, wp.vec3, zero=True),
                       ws.get(f"v_opac{w}", n, wp.float32, zero=True),
                       ws.get2d(f"v_colors{w}", n, C, wp.float32, zero=True),
                       ws.get(f"v_depths{w}", n, wp.float32, zero=True))
            accs.append(acc)

        def colors_view(a):
            if a.ndim == 2:  # worker-local (n, C) float buffer seen as (n,) vecC
                return wp.array(ptr=a.ptr, shape=(n,), dtype=colors.dtype, device=device, copy=False)
            return a

        if variant == "tile":
            if tile != TILE_LANES:
                raise ValueError(f"the tile compositing kernels need tile={TILE_LANES}, got {tile}")
            _, bwd = composite_tile_kernels(C)
            n_tiles = tiles_x * tiles_y
            bs = ws.get("tile_bwd", n_tiles * 256 * bwd_scratch_fields(C), wp.float32)
            bl = ws.get("tile_bwd_L", n_tiles * 256, wp.int32)
            gs = ws.get("tile_gsum", n_tiles * 16 * (7 + C), wp.float32)
            gout = ws.get("tile_gout", n_tiles * (7 + C), wp.float32)
            row_last = ws.get("row_last", n_tiles * 16, wp.int32)
            slot = _live_slot(device, handle)
            rec = slot.rec if slot is not None and slot.rec is not None else \
                splat_records(ws, means2d, conics, opacities, depths, colors, radii, threads)

            def launch(w, t0, t1):
                a = accs[w]
                wp.launch(bwd, dim=t1 - t0,
                          inputs=[ranges, ids, rec, width, height, tiles_x, t0, out_T, out_last, v_color, v_depth,
                                  v_alpha, bs, bl, gs, gout, row_last],
                          outputs=[a[0], a[1], a[2], colors_view(a[3]), a[4]], device=device)

            bands = _tile_bands(tiles_x * tiles_y, tiles_x, n_threads)
        else:
            _, bwd, _ = composite_kernels(C)

            def launch(w, p0, p1):
                a = accs[w]
                wp.launch(bwd, dim=p1 - p0,
                          inputs=[ranges, ids, means2d, conics, opacities, colors, depths, width, tile, tiles_x, p0,
                                  out_T, out_last, v_color, v_depth, v_alpha],
                          outputs=[a[0], a[1], a[2], colors_view(a[3]), a[4]], device=device)

            bands = _row_bands(width, height, tile, n_threads)
        run_bands(bands, n_threads, launch, bwd, device)
        base = accs[0]
        for a in accs[1:]:
            wp.launch(_add_vec2_kernel, dim=n, inputs=[a[0], base[0]], device=device)
            wp.launch(_add_vec3_kernel, dim=n, inputs=[a[1], base[1]], device=device)
            wp.launch(_add_float_kernel, dim=n, inputs=[a[2], base[2]], device=device)
            flat_dst = wp.array(ptr=v_colors.ptr, shape=(n, C), dtype=wp.float32, device=device, copy=False)
            wp.launch(_add_flat_kernel, dim=(n, C), inputs=[a[3], flat_dst], device=device)
            wp.launch(_add_float_kernel, dim=n, inputs=[a[4], base[4]], device=device)

        vm_acc = ws.get2d("v_viewmat_acc", VIEWMAT_SLOTS, 16, wp.float32, zero=True)
        per = VIEWMAT_SLOTS // max(1, n_threads)
        pre = [means, quats, scales, viewmat, K, width, height, eps2d, conics, radii, base[0], base[1], base[4]]
        launch_split(project_bwd_kernel, n, lambda i0, w: pre + [i0, w * per, per],
                     [v_means, v_quats, v_scales, vm_acc], device, threads)
        wp.launch(_sum_rows_kernel, dim=16, inputs=[vm_acc, v_viewmat], device=device)


def rasterize_backward_pose(means, quats, scales, opacities, colors, viewmat, K, width: int, height: int,
                            means2d, conics, depths, radii, out_T, out_last, handle, v_color, v_depth, v_alpha,
                            v_viewmat, tile: int = TILE_SIZE, composite: str | None = None,
                            threads: int | None = None) -> None:
    """The viewmat gradient of :func:`rasterize_forward` alone, for pose tracking against a frozen map.

    Arguments as for :func:`rasterize_backward`; writes only ``v_viewmat`` (16,) row-major. The
    compositing adjoint forms just the per-Gaussian depth, conic and mean2d cotangents (no colour
    or opacity gradients), skips pixels whose cotangents are all zero (outside a loss mask), and
    the projection adjoint computes only the camera's part, summed per chunk of ``VIEW_CHUNK``
    Gaussians and then over the chunks in order. On the CPU the result is bitwise the same for
    every thread count (see ``POSE_GROUPS``); it equals the full backward's viewmat gradient up
    to float summation order.
    """
    device = means.device
    st = _device_state(device)
    n = means.shape[0]
    C = colors.dtype._length_ if hasattr(colors.dtype, "_length_") else 1
    with st.ws.lock:
        v_viewmat.zero_()
        if n == 0:
            return
        ranges, ids, _ = lookup_binning(device, handle, means2d, conics, opacities, depths, radii,
                                        width, height, tile, threads)
        tiles_x, tiles_y = grid_dims(width, height, tile)
        n_threads = n_threads_for(device, threads)
        is_cpu = wp.get_device(device).is_cpu
        G = min(POSE_GROUPS, tiles_y) if is_cpu else 1  # CUDA: one group, atomics
        ws = st.ws
        acc = ws.get("pose_acc", G * n * POSE_NG, wp.float32, zero=True)
        pix_bwd, tile_bwd = composite_pose_kernels(C)
        if resolve_composite(composite, device) == "tile":
            if tile != TILE_LANES:
                raise ValueError(f"the tile compositing kernels need tile={TILE_LANES}, got {tile}")
            n_tiles = tiles_x * tiles_y
            bs = ws.get("tile_bwd", n_tiles * 256 * bwd_scratch_fields(C), wp.float32)
            bl = ws.get("tile_bwd_L", n_tiles * 256, wp.int32)
            gs = ws.get("tile_gsum", n_tiles * 16 * POSE_NG, wp.float32)
            gout = ws.get("tile_gout", n_tiles * POSE_NG, wp.float32)
            row_last = ws.get("row_last", n_tiles * 16, wp.int32)
            slot = _live_slot(device, handle)
            rec = slot.rec if slot is not None and slot.rec is not None else \
                splat_records(ws, means2d, conics, opacities, depths, colors, radii, threads)

            def launch(_w, grp, _grp1):
                n_rows = len(range(grp, tiles_y, G))
                wp.launch(tile_bwd, dim=n_rows * tiles_x,
                          inputs=[ranges, ids, rec, width, height, tiles_x, grp, G, grp * n, out_T, out_last,
                                  v_color, v_depth, v_alpha, bs, bl, gs, gout, row_last],
                          outputs=[acc], device=device)

            kernel = tile_bwd
        else:
            def launch(_w, grp, _grp1):
                spans = [(0, width * height)] if G == 1 else \
                    [(ty * tile * width, min(height, (ty + 1) * tile) * width) for ty in range(grp, tiles_y, G)]
                for p0, p1 in spans:
                    wp.launch(pix_bwd, dim=p1 - p0,
                              inputs=[ranges, ids, means2d, conics, opacities, colors, depths, width, tile, tiles_x,
                                      p0, grp * n, out_T, out_last, v_color, v_depth, v_alpha],
                              outputs=[acc], device=device)

            kernel = pix_bwd
        run_bands([(g, g + 1) for g in range(G)], n_threads, launch, kernel, device)

        n_chunks = (n + VIEW_CHUNK - 1) // VIEW_CHUNK
        rows = ws.get2d("pose_vm_rows", n_chunks, 16, wp.float32)
        workers = max(1, min(n_threads, n_chunks))
        bands = [(n_chunks * w // workers, n_chunks * (w + 1) // workers) for w in range(workers)]

        def reduce(_w, c0, c1):
            wp.launch(project_bwd_viewmat_kernel, dim=c1 - c0,
                      inputs=[means, quats, scales, viewmat, K, width, height, conics, radii, acc, G, c0],
                      outputs=[rows], device=device)

        run_bands([bd for bd in bands if bd[1] > bd[0]], workers, reduce, project_bwd_viewmat_kernel, device)
        wp.launch(_sum_rows_kernel, dim=16, inputs=[rows, v_viewmat], device=device)


def top_ids(means, quats, scales, opacities, viewmat, K, width: int, height: int, near: float, far: float,
            eps2d: float, tile: int = TILE_SIZE, threads: int | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Index of the Gaussian with the largest compositing weight at every pixel.

    Inputs as for :func:`rasterize_forward` (Warp arrays). Returns numpy ``(ids (H*W,) int32,
    weights (H*W,) float32)``; id -1 where no Gaussian contributes. Not differentiable: it is
    for lifting 2-D masks to the Gaussians behind them.
    """
    device = means.device
    st = _device_state(device)
    n = means.shape[0]
    with st.ws.lock:
        ws = st.ws
        means2d = ws.get("tid_means2d", n, wp.vec2)
        conics = ws.get("tid_conics", n, wp.vec3)
        depths = ws.get("tid_depths", n, wp.float32)
        radii = ws.get("tid_radii", n, wp.vec2i)
        project(means, quats, scales, opacities, viewmat, K, width, height, near, far, eps2d,
                means2d, conics, depths, radii, threads)
        ranges, ids, _ = bin_gaussians(ws, means2d, conics, opacities, depths, radii, width, height, tile,
                                       threads=threads)
        tiles_x, _ = grid_dims(width, height, tile)
        out_id = wp.empty(width * height, dtype=wp.int32, device=device)
        out_w = wp.empty(width * height, dtype=wp.float32, device=device)

        def launch(_w, p0, p1):
            wp.launch(composite_top_id, dim=p1 - p0,
                      inputs=[ranges, ids, means2d, conics, opacities, width, tile, tiles_x, p0],
                      outputs=[out_id, out_w], device=device)

        n_threads = n_threads_for(device, threads)
        run_bands(_row_bands(width, height, tile, n_threads), n_threads, launch, composite_top_id, device)
        return out_id.numpy().copy(), out_w.numpy().copy()


def count_evaluations(means2d, conics, opacities, ranges, ids, width: int, height: int,
                      tile: int = TILE_SIZE) -> int:
    """Exact number of Gaussian-pixel evaluations the forward compositing loop performs."""
    device = means2d.device
    _, _, count = composite_kernels(1)
    tiles_x, _ = grid_dims(width, height, tile)
    evals = wp.zeros(width * height, dtype=wp.int32, device=device)
    wp.launch(count, dim=width * height,
              inputs=[ranges, ids, means2d, conics, opacities, width, tile, tiles_x], outputs=[evals],
              device=device)
    return int(evals.numpy().astype(np.int64).sum())
