// The per-cell filter responses (CPU reference: `responses` in
// src/vision/detect.rs): for template cell i of a box, the object response
// F_i = w_vis_i . phi and the occlusion response plus the cell prior
// B_i + R_i = w_occ_i . phi + r_i (the unary terms of eq. 4); cells outside
// the map have zero features.
//
// `response_maps` computes them for every box location at once: the
// response of template cell i at map cell c serves every box that puts its
// cell i on c. It stores them halved, as the chain bound of
// `dense_bounds.wgsl` splits them (occluded, visible), with the CPU's order
// of summation (even feature dimensions, odd ones, then their sum).
// `responses` computes the unhalved pair at listed locations (one
// invocation per location and cell; the location index is y + 65535 z).

struct Job {
    hog_off: u32, mw: u32, mh: u32, x_lo: i32,
    y_lo: i32, nx: u32, ny: u32, weights_off: u32,
    rows: u32, cols: u32, pair: f32, chain_off: u32,
    out_off: u32, map_off: u32, pad1: u32, pad2: u32,
}

// A location: its job, the box's top-left map cell, and where its
// responses go (2 values per cell: F_i, then B_i + R_i).
struct Query {
    job: u32, x: i32, y: i32, out_off: u32,
}

@group(0) @binding(0) var<storage, read> jobs: array<Job>;
@group(0) @binding(1) var<storage, read> hog: array<f32>;
@group(0) @binding(2) var<storage, read> weights: array<f32>;
@group(0) @binding(3) var<storage, read> queries: array<Query>;
@group(0) @binding(4) var<storage, read_write> out: array<f32>;
// Per job: (occluded, visible) halved unaries, [cell i][map cell].
@group(0) @binding(5) var<storage, read_write> maps: array<vec2<f32>>;

@compute @workgroup_size(64, 1, 1)
fn response_maps(@builtin(global_invocation_id) id: vec3<u32>) {
    let j = jobs[id.z];
    let cells = j.mw * j.mh;
    let c = id.x;
    let ty = id.y;
    if (c >= cells || ty >= j.rows) {
        return;
    }
    let n = j.rows * j.cols;
    let p = j.hog_off + c * 32u;
    for (var tx = 0u; tx < j.cols; tx += 1u) {
        let i = ty * j.cols + tx;
        let wv = j.weights_off + i * 32u;
        let wo = j.weights_off + n * 32u + i * 32u;
        let r = weights[j.weights_off + 2u * n * 32u + i];
        var f0 = 0.0;
        var f1 = 0.0;
        var g0 = 0.0;
        var g1 = 0.0;
        for (var d = 0u; d < 30u; d += 2u) {
            let v0 = hog[p + d];
            let v1 = hog[p + d + 1u];
            f0 += weights[wv + d] * v0;
            g0 += weights[wo + d] * v0;
            f1 += weights[wv + d + 1u] * v1;
            g1 += weights[wo + d + 1u] * v1;
        }
        let v30 = hog[p + 30u];
        f0 += weights[wv + 30u] * v30;
        g0 += weights[wo + 30u] * v30;
        maps[j.map_off + i * cells + c] = vec2<f32>(0.5 * (g0 + g1 + r), 0.5 * (f0 + f1));
    }
}

@compute @workgroup_size(64, 1, 1)
fn responses(@builtin(global_invocation_id) id: vec3<u32>) {
    let qi = id.y + 65535u * id.z;
    if (qi >= arrayLength(&queries)) {
        return;
    }
    let q = queries[qi];
    let j = jobs[q.job];
    let n = j.rows * j.cols;
    let i = id.x;
    if (i >= n) {
        return;
    }
    let cx = q.x + i32(i % j.cols);
    let cy = q.y + i32(i / j.cols);
    let wv = j.weights_off + i * 32u;
    let wo = j.weights_off + n * 32u + i * 32u;
    var f = 0.0;
    var b = 0.0;
    if (cx >= 0 && cy >= 0 && cx < i32(j.mw) && cy < i32(j.mh)) {
        let p = j.hog_off + (u32(cy) * j.mw + u32(cx)) * 32u;
        for (var d = 0u; d < 31u; d += 1u) {
            let v = hog[p + d];
            f += weights[wv + d] * v;
            b += weights[wo + d] * v;
        }
    }
    out[q.out_off + 2u * i] = f;
    out[q.out_off + 2u * i + 1u] = b + weights[j.weights_off + 2u * n * 32u + i];
}
