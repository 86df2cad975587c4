"""The fused kernels' source (NVIDIA Warp), apart from the code that loads and launches them
(``fused_kernels``, ``fused_training_reads``): ``density_march`` (the inference marcher's density pass, one thread per
ray), ``outer_composite`` (the space beyond an object's box) and, per component counts, the reads of a grid's density
and appearance features from channels-last planes and lines with their backward (``define_training_reads``; the
renderer reads its features with them too). Each mirrors a torch function that stays the reference it is tested
against."""

# No ``from __future__ import annotations``: Warp reads the kernels' annotations, and evaluated at definition they
# may name the closures' vector types (``define_training_reads``).
from typing import Any


def define_corners(wp):
    """The Warp function every read here uses (defined anew for each module that calls it)."""
    @wp.func
    def corners(coord: wp.float32, size: int):
        # One axis of a corner-aligned, border-clamped read ([-1, 1] over ``size`` entries): the lower entry, the
        # upper one and the weight toward it (tensorial._axis_corners' rule).
        f = wp.clamp((coord + 1.0) * 0.5 * float(size - 1), 0.0, float(size - 1))
        low = wp.min(int(wp.floor(f)), wp.max(size - 2, 0))
        return low, wp.min(low + 1, size - 1), f - float(low)

    return corners


def define_kernels(wp) -> dict:
    """Build the kernels (a function so that importing this module never imports warp)."""
    corners = define_corners(wp)

    @wp.func
    def read_density(grid: wp.array3d(dtype=wp.float32), p: wp.vec3, a: wp.vec3, b: wp.vec3, relu: int) -> wp.float32:
        # grid_sample, align_corners=True, padding_mode="border": coords (x, y, z) in [-1, 1] -> grid[z, y, x].
        x0, x1, tx = corners(p[0] * a[0] + b[0], grid.shape[2])
        y0, y1, ty = corners(p[1] * a[1] + b[1], grid.shape[1])
        z0, z1, tz = corners(p[2] * a[2] + b[2], grid.shape[0])
        c00 = grid[z0, y0, x0] * (1.0 - tx) + grid[z0, y0, x1] * tx
        c01 = grid[z0, y1, x0] * (1.0 - tx) + grid[z0, y1, x1] * tx
        c10 = grid[z1, y0, x0] * (1.0 - tx) + grid[z1, y0, x1] * tx
        c11 = grid[z1, y1, x0] * (1.0 - tx) + grid[z1, y1, x1] * tx
        raw = (c00 * (1.0 - ty) + c01 * ty) * (1.0 - tz) + (c10 * (1.0 - ty) + c11 * ty) * tz
        if relu != 0:
            return wp.max(raw, 0.0)
        x = raw - 10.0  # TensoRF's shifted softplus, as torch's (linear above 20)
        if x > 20.0:
            return x
        y = wp.exp(x)
        if y < 0.01:  # log(1 + y) by its series: 1 + y rounds away y's low bits in float32 (no log1p in Warp)
            return y - 0.5 * y * y + y * y * y / 3.0
        return wp.log(1.0 + y)

    @wp.func
    def occupied(p: wp.vec3, box_min: wp.vec3, box_max: wp.vec3, mask: wp.array(dtype=wp.uint8), has_mask: int,
                 mask_min: wp.vec3, mask_max: wp.vec3, mask_res: wp.vec3i, mask_strides: wp.vec3i) -> bool:
        # FrugalNeRFField.inside: the box, then the nearest voxel of the mask padded by one False voxel.
        for k in range(3):
            if p[k] < box_min[k] or p[k] > box_max[k]:
                return False
        if has_mask == 0:
            return True
        flat = int(0)
        for k in range(3):
            idx = int(wp.rint((p[k] - mask_min[k]) / (mask_max[k] - mask_min[k]) * float(mask_res[k] - 1)))
            idx = wp.min(wp.max(idx + 1, 0), mask_res[k] + 1)
            flat += idx * mask_strides[k]
        return mask[flat] != wp.uint8(0)

    @wp.func
    def group_can_hold(occupancy: wp.array(dtype=wp.uint8), entries: wp.vec3i, a: wp.vec3, b: wp.vec3,
                       to_index: wp.vec3, rounding: int, o: wp.vec3, d: wp.vec3, t: wp.float32) -> bool:
        # BakedDensity.occupied_groups' lookup of one group centre in one dilated volume.
        flat = int(0)
        scale = int(1)
        for k in range(3):
            f = (o[k] * a[k] + b[k] + 1.0) * to_index[k] + d[k] * a[k] * to_index[k] * t
            if rounding != 0:
                f = wp.rint(f)
            else:
                f = wp.floor(f)
            i = wp.min(int(wp.max(f, 0.0)), entries[k] - 1)
            flat += i * scale
            scale *= entries[k]
        return occupancy[flat] != wp.uint8(0)

    @wp.kernel
    def density_march(
        origins: wp.array(dtype=wp.vec3), directions: wp.array(dtype=wp.vec3),
        t_near: wp.array(dtype=wp.float32), t_far: wp.array(dtype=wp.float32),
        outputs_at: wp.array(dtype=wp.int32), num_groups: int, num_bounds: int,
        occupancy0: wp.array(dtype=wp.uint8), entries0: wp.vec3i, a0: wp.vec3, b0: wp.vec3, to_index0: wp.vec3,
        rounding0: int,
        occupancy1: wp.array(dtype=wp.uint8), entries1: wp.vec3i, a1: wp.vec3, b1: wp.vec3, to_index1: wp.vec3,
        rounding1: int,
        grid: wp.array3d(dtype=wp.float32), grid_a: wp.vec3, grid_b: wp.vec3, relu: int,
        box_min: wp.vec3, box_max: wp.vec3,
        mask: wp.array(dtype=wp.uint8), has_mask: int, mask_min: wp.vec3, mask_max: wp.vec3,
        mask_res: wp.vec3i, mask_strides: wp.vec3i,
        step: wp.float32, num_samples: int, group: int, per_block: int, delta: wp.float32,
        weight_threshold: wp.float32, faint_weight: wp.float32, faint_budget: wp.float32,
        stop_optical: wp.float32, max_optical: wp.float32,
        sums: wp.array2d(dtype=wp.float32), shade_t: wp.array(dtype=wp.float32), shade_w: wp.array(dtype=wp.float32),
    ):
        r = wp.tid()
        o = origins[r]
        d = directions[r]
        near = t_near[r]
        far = t_far[r]
        out = outputs_at[r]  # this ray's first row of the shade list (its marched slots bound its rows)
        optical_sum = wp.float32(0.0)
        accumulation = wp.float32(0.0)
        weighted_t = wp.float32(0.0)
        left = wp.float32(0.0)  # weight whose colour was left out (the faint budget)
        running = wp.float32(0.0)
        rank = int(0)
        count = int(0)
        finished = bool(False)
        for g in range(num_groups):
            if finished:
                break
            # The group's first slot in the segment, and density possible somewhere in it (occupied_groups).
            wanted = near + (float(g * group) + 0.5) * step < far
            centre = near + (float(g * group) + 0.5 * float(group)) * step
            if wanted and num_bounds > 0:
                wanted = group_can_hold(occupancy0, entries0, a0, b0, to_index0, rounding0, o, d, centre)
            if wanted and num_bounds > 1:
                wanted = group_can_hold(occupancy1, entries1, a1, b1, to_index1, rounding1, o, d, centre)
            if wanted:
                if rank % per_block == 0:
                    if rank > 0 and optical_sum >= stop_optical:
                        break
                    running = left
                rank += 1
                for k in range(group):
                    if finished:
                        break
                    i = g * group + k
                    t = near + (float(i) + 0.5) * step
                    if i < num_samples and t < far:
                        p = o + d * t
                        density = wp.float32(0.0)
                        if occupied(p, box_min, box_max, mask, has_mask, mask_min, mask_max, mask_res, mask_strides):
                            density = read_density(grid, p, grid_a, grid_b, relu)
                        tau = wp.clamp(density * delta, 0.0, max_optical)
                        # A slot without density adds nothing (its weight is exactly 0): no exps.
                        w = wp.float32(0.0)
                        if tau > 0.0:
                            w = (1.0 - wp.exp(-tau)) * wp.exp(-optical_sum)
                            optical_sum = optical_sum + tau
                            accumulation = accumulation + w
                            weighted_t = weighted_t + w * t
                            if optical_sum >= stop_optical:
                                finished = True
                        if w > weight_threshold:
                            shade = True
                            if faint_budget > 0.0 and w < faint_weight:
                                running = running + w
                                if running <= faint_budget:
                                    left = left + w
                                    shade = False
                            if shade:
                                shade_t[out + count] = t
                                shade_w[out + count] = w
                                count += 1
        sums[r, 0] = accumulation
        sums[r, 1] = weighted_t
        sums[r, 2] = float(count)

    @wp.func
    def contract_point(p: wp.vec3, centre: wp.vec3, half: wp.vec3) -> wp.vec3:
        # geometry.contraction.contract: box units, the box as it is, beyond it into [-2, 2]^3.
        q = wp.vec3((p[0] - centre[0]) / half[0], (p[1] - centre[1]) / half[1], (p[2] - centre[2]) / half[2])
        norm = wp.max(wp.max(wp.abs(q[0]), wp.abs(q[1])), wp.abs(q[2]))
        if norm > 1.0:
            return q * ((2.0 - 1.0 / norm) / norm)
        return q

    @wp.kernel
    def outer_composite(
        origins: wp.array(dtype=wp.vec3), directions: wp.array(dtype=wp.vec3),
        edges: wp.array2d(dtype=wp.float32), t: wp.array2d(dtype=wp.float32),
        table: wp.array2d(dtype=wp.float32), dims: wp.vec3i, centre: wp.vec3, half: wp.vec3,
        distance_scale: wp.float32, max_optical: wp.float32, sums: wp.array2d(dtype=wp.float32),
    ):
        # OuterSpace._composite outside training: each sample's share of the ray is its bin's length in the
        # contracted space; density and colour logits from the baked node table (trilinear_rows' rule).
        r = wp.tid()
        o = origins[r]
        d = directions[r]
        optical_sum = wp.float32(0.0)
        accumulation = wp.float32(0.0)
        red = wp.float32(0.0)
        green = wp.float32(0.0)
        blue = wp.float32(0.0)
        disparity = wp.float32(0.0)
        previous = contract_point(o + d * edges[r, 0], centre, half)
        for i in range(t.shape[1]):
            edge = contract_point(o + d * edges[r, i + 1], centre, half)
            delta = wp.length(edge - previous)
            previous = edge
            ti = t[r, i]
            c = contract_point(o + d * ti, centre, half) * 0.5  # [-2, 2] to the grid's [-1, 1]
            low = wp.vec3i(0, 0, 0)
            w = wp.vec3(0.0, 0.0, 0.0)
            for k in range(3):
                f = wp.min(wp.max((c[k] + 1.0) * 0.5 * float(dims[k] - 1), 0.0), float(dims[k] - 1))
                lo = wp.min(wp.floor(f), wp.max(float(dims[k] - 2), 0.0))
                low[k] = int(lo)
                w[k] = f - lo
            x_step = int(0)
            y_step = int(0)
            z_step = int(0)
            if dims[0] > 1:
                x_step = 1
            if dims[1] > 1:
                y_step = dims[0]
            if dims[2] > 1:
                z_step = dims[0] * dims[1]
            base = (low[2] * dims[1] + low[1]) * dims[0] + low[0]
            values = wp.vec4(0.0, 0.0, 0.0, 0.0)
            for ch in range(4):
                n0 = table[base, ch] + w[0] * (table[base + x_step, ch] - table[base, ch])
                n1 = table[base + y_step, ch] + w[0] * (table[base + y_step + x_step, ch] - table[base + y_step, ch])
                n2 = table[base + z_step, ch] + w[0] * (table[base + z_step + x_step, ch] - table[base + z_step, ch])
                n3 = table[base + z_step + y_step, ch] + w[0] * (
                    table[base + z_step + y_step + x_step, ch] - table[base + z_step + y_step, ch])
                near_z = n0 + w[1] * (n1 - n0)
                far_z = n2 + w[1] * (n3 - n2)
                values[ch] = near_z + w[2] * (far_z - near_z)
            density = wp.max(values[0], 0.0)
            tau = wp.clamp(density * delta * distance_scale, 0.0, max_optical)
            weight = (1.0 - wp.exp(-tau)) * wp.exp(-optical_sum)
            optical_sum = optical_sum + tau
            accumulation = accumulation + weight
            red = red + weight / (1.0 + wp.exp(-values[1]))
            green = green + weight / (1.0 + wp.exp(-values[2]))
            blue = blue + weight / (1.0 + wp.exp(-values[3]))
            disparity = disparity + weight / ti
        sums[r, 0] = accumulation
        sums[r, 1] = red
        sums[r, 2] = green
        sums[r, 3] = blue
        sums[r, 4] = disparity

    return {"module": density_march.module, "density_march": density_march, "outer_composite": outer_composite}


def define_training_reads(wp, components) -> dict:
    """A training step's reads (and the renderer's feature reads) of a grid whose planes and lines have ``components`` (XY, XZ, YZ) channels, in a
    module of their own per component counts: ``density_read`` (``TensorVMGrid.plane_line_products`` summed over
    planes and channels), ``feature_read`` (the products concatenated: the appearance features) and their backward
    kernels, which add the planes' and lines' gradient into tables; and ``vectors``, ``row``, the three planes'
    vector types and the features' row type. The tensors are channels-last copies of the full planes and lines, read
    at a stride's view's entries times the stride (as ``tensorial.sample_plane`` reads them): a corner is one vector
    load of a plane's channels, so a read is a few vector loads and its arithmetic runs in SIMD (1.7x the same read
    channel by channel, a scalar loop with a stride per access, on 262,144 points)."""
    c0, c1, c2 = (int(c) for c in components)
    vec0, vec1, vec2 = (wp.types.vector(length=c, dtype=wp.float32) for c in (c0, c1, c2))
    row = wp.types.vector(length=c0 + c1 + c2, dtype=wp.float32)
    c01 = c0 + c1

    corners = define_corners(wp)

    @wp.func
    def plane_line(plane: wp.array(dtype=Any), row: int, width: int, height: int, line: wp.array(dtype=Any),
                   length: int, stride: int, x: wp.float32, y: wp.float32, z: wp.float32):
        # sample_plane and sample_line on the stride's views, every channel at once: the plane's and the line's value.
        x0, x1, tx = corners(x, width)
        y0, y1, ty = corners(y, height)
        z0, z1, tz = corners(z, length)
        r0 = y0 * stride * row
        r1 = y1 * stride * row
        value = (plane[r0 + x0 * stride] * (1.0 - tx) + plane[r0 + x1 * stride] * tx) * (1.0 - ty) + (
            plane[r1 + x0 * stride] * (1.0 - tx) + plane[r1 + x1 * stride] * tx) * ty
        near = line[z0 * stride]
        return value, near + (line[z1 * stride] - near) * tz

    @wp.func
    def plane_line_backward(plane: wp.array(dtype=Any), row: int, width: int, height: int, line: wp.array(dtype=Any),
                            length: int, stride: int, x: wp.float32, y: wp.float32, z: wp.float32, grad: Any,
                            plane_grad: wp.array(dtype=Any), line_grad: wp.array(dtype=Any)):
        # d(plane * line) / d corners, channel by channel, for the products' gradient ``grad``: the line's value
        # times each plane corner's weight, the plane's value times each line entry's weight; added into this
        # launch's own gradient tables.
        # (The corners again: plane_line's are inlined beside them, and the compiler computes them once.)
        plane_value, line_value = plane_line(plane, row, width, height, line, length, stride, x, y, z)
        x0, x1, tx = corners(x, width)
        y0, y1, ty = corners(y, height)
        z0, z1, tz = corners(z, length)
        r0 = y0 * stride * row
        r1 = y1 * stride * row
        by_line = wp.cw_mul(line_value, grad)
        wp.atomic_add(plane_grad, r0 + x0 * stride, by_line * ((1.0 - tx) * (1.0 - ty)))
        wp.atomic_add(plane_grad, r0 + x1 * stride, by_line * (tx * (1.0 - ty)))
        wp.atomic_add(plane_grad, r1 + x0 * stride, by_line * ((1.0 - tx) * ty))
        wp.atomic_add(plane_grad, r1 + x1 * stride, by_line * (tx * ty))
        by_plane = wp.cw_mul(plane_value, grad)
        wp.atomic_add(line_grad, z0 * stride, by_plane * (1.0 - tz))
        wp.atomic_add(line_grad, z1 * stride, by_plane * tz)

    # PLANE_AXES: XY with line Z, XZ with line Y, YZ with line X; ``sizes`` the views' entries along x, y, z and
    # ``rows`` the full planes' widths (X, X, Y).
    @wp.kernel(module="unique", enable_backward=False)
    def density_read(
        coords: wp.array(dtype=wp.vec3), sizes: wp.vec3i, rows: wp.vec3i, stride: int,
        plane0: wp.array(dtype=vec0), line0: wp.array(dtype=vec0),
        plane1: wp.array(dtype=vec1), line1: wp.array(dtype=vec1),
        plane2: wp.array(dtype=vec2), line2: wp.array(dtype=vec2),
        out: wp.array(dtype=wp.float32),
    ):
        i = wp.tid()
        c = coords[i]
        p0, l0 = plane_line(plane0, rows[0], sizes[0], sizes[1], line0, sizes[2], stride, c[0], c[1], c[2])
        p1, l1 = plane_line(plane1, rows[1], sizes[0], sizes[2], line1, sizes[1], stride, c[0], c[2], c[1])
        p2, l2 = plane_line(plane2, rows[2], sizes[1], sizes[2], line2, sizes[0], stride, c[1], c[2], c[0])
        out[i] = wp.dot(p0, l0) + wp.dot(p1, l1) + wp.dot(p2, l2)

    @wp.kernel(module="unique", enable_backward=False)
    def density_read_backward(
        coords: wp.array(dtype=wp.vec3), sizes: wp.vec3i, rows: wp.vec3i, stride: int,
        plane0: wp.array(dtype=vec0), line0: wp.array(dtype=vec0),
        plane1: wp.array(dtype=vec1), line1: wp.array(dtype=vec1),
        plane2: wp.array(dtype=vec2), line2: wp.array(dtype=vec2),
        grad: wp.array(dtype=wp.float32),
        plane_grad0: wp.array(dtype=vec0), line_grad0: wp.array(dtype=vec0),
        plane_grad1: wp.array(dtype=vec1), line_grad1: wp.array(dtype=vec1),
        plane_grad2: wp.array(dtype=vec2), line_grad2: wp.array(dtype=vec2),
    ):
        i = wp.tid()
        g = grad[i]
        if g == 0.0:  # a sample whose activation cut it (ReLU below 0) or that no loss reads adds nothing
            return
        c = coords[i]
        plane_line_backward(plane0, rows[0], sizes[0], sizes[1], line0, sizes[2], stride, c[0], c[1], c[2], vec0(g),
                            plane_grad0, line_grad0)
        plane_line_backward(plane1, rows[1], sizes[0], sizes[2], line1, sizes[1], stride, c[0], c[2], c[1], vec1(g),
                            plane_grad1, line_grad1)
        plane_line_backward(plane2, rows[2], sizes[1], sizes[2], line2, sizes[0], stride, c[1], c[2], c[0], vec2(g),
                            plane_grad2, line_grad2)

    @wp.kernel(module="unique", enable_backward=False)
    def feature_read(
        coords: wp.array(dtype=wp.vec3), sizes: wp.vec3i, rows: wp.vec3i, stride: int,
        plane0: wp.array(dtype=vec0), line0: wp.array(dtype=vec0),
        plane1: wp.array(dtype=vec1), line1: wp.array(dtype=vec1),
        plane2: wp.array(dtype=vec2), line2: wp.array(dtype=vec2),
        out: wp.array(dtype=row),
    ):
        i = wp.tid()
        c = coords[i]
        p0, l0 = plane_line(plane0, rows[0], sizes[0], sizes[1], line0, sizes[2], stride, c[0], c[1], c[2])
        p1, l1 = plane_line(plane1, rows[1], sizes[0], sizes[2], line1, sizes[1], stride, c[0], c[2], c[1])
        p2, l2 = plane_line(plane2, rows[2], sizes[1], sizes[2], line2, sizes[0], stride, c[1], c[2], c[0])
        a = wp.cw_mul(p0, l0)
        b = wp.cw_mul(p1, l1)
        e = wp.cw_mul(p2, l2)
        features = row()
        for k in range(c0):
            features[k] = a[k]
        for k in range(c1):
            features[c0 + k] = b[k]
        for k in range(c2):
            features[c01 + k] = e[k]
        out[i] = features

    @wp.kernel(module="unique", enable_backward=False)
    def feature_read_backward(
        coords: wp.array(dtype=wp.vec3), sizes: wp.vec3i, rows: wp.vec3i, stride: int,
        plane0: wp.array(dtype=vec0), line0: wp.array(dtype=vec0),
        plane1: wp.array(dtype=vec1), line1: wp.array(dtype=vec1),
        plane2: wp.array(dtype=vec2), line2: wp.array(dtype=vec2),
        grad: wp.array(dtype=row),
        plane_grad0: wp.array(dtype=vec0), line_grad0: wp.array(dtype=vec0),
        plane_grad1: wp.array(dtype=vec1), line_grad1: wp.array(dtype=vec1),
        plane_grad2: wp.array(dtype=vec2), line_grad2: wp.array(dtype=vec2),
    ):
        i = wp.tid()
        g = grad[i]
        c = coords[i]
        g0 = vec0()
        g1 = vec1()
        g2 = vec2()
        for k in range(c0):
            g0[k] = g[k]
        for k in range(c1):
            g1[k] = g[c0 + k]
        for k in range(c2):
            g2[k] = g[c01 + k]
        plane_line_backward(plane0, rows[0], sizes[0], sizes[1], line0, sizes[2], stride, c[0], c[1], c[2], g0,
                            plane_grad0, line_grad0)
        plane_line_backward(plane1, rows[1], sizes[0], sizes[2], line1, sizes[1], stride, c[0], c[2], c[1], g1,
                            plane_grad1, line_grad1)
        plane_line_backward(plane2, rows[2], sizes[1], sizes[2], line2, sizes[0], stride, c[1], c[2], c[0], g2,
                            plane_grad2, line_grad2)

    def channels_first(vector, channels: int):
        @wp.kernel(module="unique", enable_backward=False)
        def to_channels_first(table: wp.array(dtype=vector), out: wp.array2d(dtype=wp.float32)):
            # A gradient table [n, C] as [C, n]: each row read as one vector, written as C entries n apart (torch's
            # transposing copy of a 48-channel plane took ~3x as long).
            r = wp.tid()
            v = table[r]
            for k in range(channels):
                out[k, r] = v[k]

        return to_channels_first

    return {"density_read": density_read, "density_read_backward": density_read_backward,
            "feature_read": feature_read, "feature_read_backward": feature_read_backward,
            "channels_first": [channels_first(v, c) for v, c in ((vec0, c0), (vec1, c1), (vec2, c2))],
            "vectors": (vec0, vec1, vec2), "row": row}
