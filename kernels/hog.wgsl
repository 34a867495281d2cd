// Felzenszwalb et al. 31-d HOG of every pyramid level at once (CPU
// reference: `hog` in src/vision/hog.rs, same layout: 32 values per cell,
// the last one zero). Three passes: per pixel the gradient of the channel
// with the largest magnitude and its orientation bin; per cell the gathered
// bilinear votes (in the CPU's order: pixel rows top to bottom, then left to
// right); per cell the block normalisation, truncation and projection.
// Workgroup z is the level.

struct Level {
    src_w: u32, src_h: u32, src_off: u32, dst_w: u32,
    dst_h: u32, dst_off: u32, tmp_off: u32, xtap_off: u32,
    ytap_off: u32, cw: u32, ch: u32, hist_off: u32,
    hog_off: u32, grad_off: u32, pad0: u32, pad1: u32,
}

@group(0) @binding(0) var<storage, read> levels: array<Level>;
// The resized level images (interleaved RGB).
@group(0) @binding(1) var<storage, read> img: array<f32>;
// Per level pixel: magnitude, and the bin as bits (0..18; 255: no vote).
@group(0) @binding(2) var<storage, read_write> grad: array<vec2<f32>>;
@group(0) @binding(3) var<storage, read_write> hist: array<f32>;
@group(0) @binding(4) var<storage, read_write> hog: array<f32>;

const CELL: u32 = 8u;
const SBINS: u32 = 18u;
const TRUNC: f32 = 0.2;
const NORM_EPS: f32 = 1e-4;
const TEXTURE_WEIGHT: f32 = 0.2357;

var<private> UU: array<f32, 9> = array<f32, 9>(1.0000, 0.9397, 0.7660, 0.5000, 0.1736, -0.1736, -0.5000, -0.7660, -0.9397);
var<private> VV: array<f32, 9> = array<f32, 9>(0.0000, 0.3420, 0.6428, 0.8660, 0.9848, 0.9848, 0.8660, 0.6428, 0.3420);

fn px(lv: Level, x: u32, y: u32, c: u32) -> f32 {
    return img[lv.dst_off + (y * lv.dst_w + x) * 3u + c];
}

@compute @workgroup_size(8, 8, 1)
fn gradient(@builtin(global_invocation_id) id: vec3<u32>) {
    let lv = levels[id.z];
    let x = id.x;
    let y = id.y;
    let w = lv.dst_w;
    let h = lv.dst_h;
    if (x >= w || y >= h) {
        return;
    }
    // Central differences, clamped at the borders (at x = 0 the CPU takes
    // r[1] - r[0], at x = w - 1 r[w - 1] - r[w - 2]).
    let xl = select(x - 1u, 0u, x == 0u);
    let xr = min(x + 1u, w - 1u);
    let yu = select(y - 1u, 0u, y == 0u);
    let yd = min(y + 1u, h - 1u);
    var best_m = -1.0;
    var gx = 0.0;
    var gy = 0.0;
    for (var c = 0u; c < 3u; c += 1u) {
        let dx = px(lv, xr, y, c) - px(lv, xl, y, c);
        let dy = px(lv, x, yd, c) - px(lv, x, yu, c);
        let m = dx * dx + dy * dy;
        if (m > best_m) {
            best_m = m;
            gx = dx;
            gy = dy;
        }
    }
    var best = 0.0;
    var bin = 0u;
    for (var o = 0u; o < 9u; o += 1u) {
        let dot = UU[o] * gx + VV[o] * gy;
        if (dot > best) {
            best = dot;
            bin = o;
        } else if (-dot > best) {
            best = -dot;
            bin = o + 9u;
        }
    }
    grad[lv.grad_off + y * w + x] = vec2<f32>(sqrt(best_m), bitcast<f32>(bin));
}

// Cell-space coordinate of a pixel centre.
fn cell_coord(p: u32) -> f32 {
    return (f32(p) + 0.5) / 8.0 - 0.5;
}

@compute @workgroup_size(8, 8, 1)
fn histogram(@builtin(global_invocation_id) id: vec3<u32>) {
    let lv = levels[id.z];
    let cx = id.x;
    let cy = id.y;
    if (cx >= lv.cw || cy >= lv.ch) {
        return;
    }
    var hc: array<f32, 18>;
    for (var o = 0u; o < SBINS; o += 1u) {
        hc[o] = 0.0;
    }
    // Pixels whose two nearest cell centres include this cell.
    let x0 = max(i32(cx * CELL) - 4, 0);
    let x1 = min(i32(cx * CELL) + 12, i32(lv.dst_w));
    let y0 = max(i32(cy * CELL) - 4, 0);
    let y1 = min(i32(cy * CELL) + 12, i32(lv.dst_h));
    for (var y = y0; y < y1; y += 1) {
        let yp = cell_coord(u32(y));
        let iy = floor(yp);
        let vy0 = yp - iy;
        let wy = select(vy0, 1.0 - vy0, i32(iy) == i32(cy));
        for (var x = x0; x < x1; x += 1) {
            let g = grad[lv.grad_off + u32(y) * lv.dst_w + u32(x)];
            let mag = g.x;
            if (mag == 0.0) {
                continue;
            }
            let xp = cell_coord(u32(x));
            let ix = floor(xp);
            let vx0 = xp - ix;
            let wx = select(vx0 * mag, (1.0 - vx0) * mag, i32(ix) == i32(cx));
            let b = bitcast<u32>(g.y);
            hc[b] += wx * wy;
        }
    }
    let base = lv.hist_off + (cy * lv.cw + cx) * SBINS;
    for (var o = 0u; o < SBINS; o += 1u) {
        hist[base + o] = hc[o];
    }
}

// Gradient energy of a cell (zero outside the map).
fn energy(lv: Level, x: i32, y: i32) -> f32 {
    if (x < 0 || y < 0 || x >= i32(lv.cw) || y >= i32(lv.ch)) {
        return 0.0;
    }
    let base = lv.hist_off + (u32(y) * lv.cw + u32(x)) * SBINS;
    var e = 0.0;
    for (var o = 0u; o < 9u; o += 1u) {
        let s = hist[base + o] + hist[base + o + 9u];
        e += s * s;
    }
    return e;
}

@compute @workgroup_size(8, 8, 1)
fn normalise(@builtin(global_invocation_id) id: vec3<u32>) {
    let lv = levels[id.z];
    let cx = id.x;
    let cy = id.y;
    if (cx >= lv.cw || cy >= lv.ch) {
        return;
    }
    let x = i32(cx);
    let y = i32(cy);
    // n(dx, dy) of the CPU is the energy of cell (x + dx - 1, y + dy - 1).
    let n00 = energy(lv, x - 1, y - 1);
    let n10 = energy(lv, x, y - 1);
    let n20 = energy(lv, x + 1, y - 1);
    let n01 = energy(lv, x - 1, y);
    let n11 = energy(lv, x, y);
    let n21 = energy(lv, x + 1, y);
    let n02 = energy(lv, x - 1, y + 1);
    let n12 = energy(lv, x, y + 1);
    let n22 = energy(lv, x + 1, y + 1);
    let n1 = 1.0 / sqrt(n11 + n21 + n12 + n22 + NORM_EPS);
    let n2 = 1.0 / sqrt(n10 + n20 + n11 + n21 + NORM_EPS);
    let n3 = 1.0 / sqrt(n01 + n11 + n02 + n12 + NORM_EPS);
    let n4 = 1.0 / sqrt(n00 + n10 + n01 + n11 + NORM_EPS);
    let hb = lv.hist_off + (cy * lv.cw + cx) * SBINS;
    let dst = lv.hog_off + (cy * lv.cw + cx) * 32u;
    var t = vec4<f32>(0.0, 0.0, 0.0, 0.0);
    for (var o = 0u; o < SBINS; o += 1u) {
        let hv = hist[hb + o];
        let h4 = min(vec4<f32>(hv * n1, hv * n2, hv * n3, hv * n4), vec4<f32>(TRUNC));
        hog[dst + o] = 0.5 * (((h4.x + h4.y) + h4.z) + h4.w);
        t += h4;
    }
    for (var o = 0u; o < 9u; o += 1u) {
        let s = hist[hb + o] + hist[hb + o + 9u];
        let h4 = min(vec4<f32>(s * n1, s * n2, s * n3, s * n4), vec4<f32>(TRUNC));
        hog[dst + SBINS + o] = 0.5 * (((h4.x + h4.y) + h4.z) + h4.w);
    }
    hog[dst + 27u] = TEXTURE_WEIGHT * t.x;
    hog[dst + 28u] = TEXTURE_WEIGHT * t.y;
    hog[dst + 29u] = TEXTURE_WEIGHT * t.z;
    hog[dst + 30u] = TEXTURE_WEIGHT * t.w;
    hog[dst + 31u] = 0.0;
}
