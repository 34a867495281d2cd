// Learned cells (CPU reference: `Backbone::forward` in src/vision/cnn.rs and
// `CellProjection::project` in src/vision/cells.rs): the truncated
// EfficientNet-Lite0 backbone's three operations and the projection of its
// 40 channels onto a cell's 31 numbers, in HOG's layout.
//
// One dispatch per layer; `layer` is bound at that layer's own offset of
// the descriptor buffer. Maps are channels first: channel c's (x, y) at
// `(c * h + y) * w + x` (after `src_off` / `dst_off`). Padding is
// TensorFlow's "same" (`left`, `top` samples before the first; the rest
// after), so samples outside the map count zero. Sums run in the CPU's
// order of terms within a dot product (the CPU's GEMM may block them
// differently, hence the tolerance of tests/gpu_parity.rs).

struct Layer {
    in_w: u32, in_h: u32, out_w: u32, out_h: u32,
    cin: u32, cout: u32, k: u32, stride: u32,
    left: u32, top: u32, w_off: u32, b_off: u32,
    src_off: u32, dst_off: u32, flags: u32, pad0: u32,
}

// flags
const RELU6: u32 = 1u;
const SKIP: u32 = 2u;

@group(0) @binding(0) var<storage, read> layer: Layer;
@group(0) @binding(1) var<storage, read> weights: array<f32>;
@group(0) @binding(2) var<storage, read> src: array<f32>;
@group(0) @binding(3) var<storage, read_write> dst: array<f32>;
@group(0) @binding(4) var<storage, read> skip: array<f32>;

// The input coordinate of output `o`'s tap `d`, or -1 outside the map.
fn tap(o: u32, d: u32, stride: u32, before: u32, n: u32) -> i32 {
    let i = i32(o * stride + d) - i32(before);
    if (i < 0 || i >= i32(n)) {
        return -1;
    }
    return i;
}

// The stem: 3x3, stride 2, over the normalised RGB level image (interleaved,
// 0-255). Weights `cout x 3 x 3 x 3` at w_off; at b_off the biases, then the
// input mean and standard deviation of each colour.
@compute @workgroup_size(8, 8, 1)
fn stem(@builtin(global_invocation_id) id: vec3<u32>) {
    let l = layer;
    let ox = id.x;
    let oy = id.y;
    let co = id.z;
    if (ox >= l.out_w || oy >= l.out_h || co >= l.cout) {
        return;
    }
    var acc = 0.0;
    for (var c = 0u; c < 3u; c += 1u) {
        let mu = weights[l.b_off + l.cout + c];
        let sigma = weights[l.b_off + l.cout + 3u + c];
        for (var dy = 0u; dy < 3u; dy += 1u) {
            let y = tap(oy, dy, 2u, l.top, l.in_h);
            for (var dx = 0u; dx < 3u; dx += 1u) {
                let x = tap(ox, dx, 2u, l.left, l.in_w);
                if (y < 0 || x < 0) {
                    continue;
                }
                let v = (src[l.src_off + (u32(y) * l.in_w + u32(x)) * 3u + c] - mu) / sigma;
                acc += weights[l.w_off + ((co * 3u + c) * 3u + dy) * 3u + dx] * v;
            }
        }
    }
    dst[l.dst_off + (co * l.out_h + oy) * l.out_w + ox] = clamp(acc + weights[l.b_off + co], 0.0, 6.0);
}

// A pointwise (1x1) convolution: `cout x cin` weights, a bias per output;
// then ReLU6 (expansion) or the block's input added (projection, SKIP).
@compute @workgroup_size(8, 8, 1)
fn pointwise(@builtin(global_invocation_id) id: vec3<u32>) {
    let l = layer;
    let x = id.x;
    let y = id.y;
    let co = id.z;
    if (x >= l.out_w || y >= l.out_h || co >= l.cout) {
        return;
    }
    let plane = l.out_w * l.out_h;
    let p = y * l.out_w + x;
    var acc = 0.0;
    for (var i = 0u; i < l.cin; i += 1u) {
        acc += weights[l.w_off + co * l.cin + i] * src[l.src_off + i * plane + p];
    }
    let b = weights[l.b_off + co];
    var v: f32;
    if ((l.flags & SKIP) != 0u) {
        v = acc + (b + skip[co * plane + p]);
    } else {
        v = acc + b;
    }
    if ((l.flags & RELU6) != 0u) {
        v = clamp(v, 0.0, 6.0);
    }
    dst[l.dst_off + co * plane + p] = v;
}

// A depthwise `k x k` convolution of stride `stride`: `cout x k x k`
// weights, a bias per channel, then ReLU6.
@compute @workgroup_size(8, 8, 1)
fn depthwise(@builtin(global_invocation_id) id: vec3<u32>) {
    let l = layer;
    let ox = id.x;
    let oy = id.y;
    let c = id.z;
    if (ox >= l.out_w || oy >= l.out_h || c >= l.cout) {
        return;
    }
    let plane = l.in_w * l.in_h;
    var acc = weights[l.b_off + c];
    for (var dy = 0u; dy < l.k; dy += 1u) {
        let y = tap(oy, dy, l.stride, l.top, l.in_h);
        if (y < 0) {
            continue;
        }
        for (var dx = 0u; dx < l.k; dx += 1u) {
            let x = tap(ox, dx, l.stride, l.left, l.in_w);
            if (x < 0) {
                continue;
            }
            acc += weights[l.w_off + (c * l.k + dy) * l.k + dx]
                * src[l.src_off + c * plane + u32(y) * l.in_w + u32(x)];
        }
    }
    dst[l.dst_off + (c * l.out_h + oy) * l.out_w + ox] = clamp(acc, 0.0, 6.0);
}

// The cells: the first `out_w x out_h` cells of the backbone's `in_w x
// in_h` map, each `basis (cout x cin) * features - bias` in HOG's layout
// (32 numbers a cell, the last zero).
@compute @workgroup_size(8, 8, 1)
fn cells(@builtin(global_invocation_id) id: vec3<u32>) {
    let l = layer;
    let x = id.x;
    let y = id.y;
    if (x >= l.out_w || y >= l.out_h) {
        return;
    }
    let plane = l.in_w * l.in_h;
    let o = l.dst_off + (y * l.out_w + x) * 32u;
    for (var k = 0u; k < l.cout; k += 1u) {
        var acc = 0.0;
        for (var a = 0u; a < l.cin; a += 1u) {
            acc += src[l.src_off + a * plane + y * l.in_w + x] * weights[l.w_off + k * l.cin + a];
        }
        dst[o + k] = acc - weights[l.b_off + k];
    }
    for (var k = l.cout; k < 32u; k += 1u) {
        dst[o + k] = 0.0;
    }
}
