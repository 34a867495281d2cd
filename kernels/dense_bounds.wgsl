// The exact-pruning lower bound of every box location of every level and
// viewpoint (CPU reference: `dense_bounds` in src/vision/detect.rs): the
// row-and-column chain decomposition of the unary and Potts energy. Half of
// every cell's unaries goes to the chain of its template row, half to the
// chain of its column; each chain is minimised exactly by dynamic
// programming (`chains`, one invocation per location and chain), and the
// chain minima of a location add up to its bound (`sum_chains`, rows first,
// then columns, as on the CPU). The unaries are the response maps of
// `responses.wgsl` (`response_maps`), halved; cells outside the map have
// zero features, so only their prior counts. Workgroup z is the job (one
// level and viewpoint).

struct Job {
    hog_off: u32, mw: u32, mh: u32, x_lo: i32,
    y_lo: i32, nx: u32, ny: u32, weights_off: u32,
    rows: u32, cols: u32, pair: f32, chain_off: u32,
    out_off: u32, map_off: u32, pad1: u32, pad2: u32,
}

@group(0) @binding(0) var<storage, read> jobs: array<Job>;
// Per view: object filters (cells x 32), occlusion filters (cells x 32),
// then the per-cell prior (cells).
@group(0) @binding(2) var<storage, read> weights: array<f32>;
@group(0) @binding(3) var<storage, read_write> chain_min: array<f32>;
@group(0) @binding(4) var<storage, read_write> bounds: array<f32>;
@group(0) @binding(5) var<storage, read> maps: array<vec2<f32>>;

// Halved unaries (u0: occluded, u1: visible) of template cell (tx, ty) of
// the box at top-left map cell (bx, by).
fn half_unaries(j: Job, bx: i32, by: i32, tx: u32, ty: u32) -> vec2<f32> {
    let i = ty * j.cols + tx;
    let cx = bx + i32(tx);
    let cy = by + i32(ty);
    if (cx >= 0 && cy >= 0 && cx < i32(j.mw) && cy < i32(j.mh)) {
        return maps[j.map_off + i * j.mw * j.mh + u32(cy) * j.mw + u32(cx)];
    }
    let n = j.rows * j.cols;
    let r = weights[j.weights_off + 2u * n * 32u + i];
    return vec2<f32>(0.5 * (0.0 + 0.0 + r), 0.0);
}

@compute @workgroup_size(64, 1, 1)
fn chains(@builtin(global_invocation_id) id: vec3<u32>) {
    let j = jobs[id.z];
    let loc = id.x;
    let c = id.y;
    let nchains = j.rows + j.cols;
    if (loc >= j.nx * j.ny || c >= nchains) {
        return;
    }
    let bx = j.x_lo + i32(loc % j.nx);
    let by = j.y_lo + i32(loc / j.nx);
    var s = vec2<f32>(0.0, 0.0);
    if (c < j.rows) {
        s = half_unaries(j, bx, by, 0u, c);
        for (var tx = 1u; tx < j.cols; tx += 1u) {
            let u = half_unaries(j, bx, by, tx, c);
            s = vec2<f32>(u.x + min(s.x, s.y + j.pair), u.y + min(s.y, s.x + j.pair));
        }
    } else {
        let tx = c - j.rows;
        s = half_unaries(j, bx, by, tx, 0u);
        for (var ty = 1u; ty < j.rows; ty += 1u) {
            let u = half_unaries(j, bx, by, tx, ty);
            s = vec2<f32>(u.x + min(s.x, s.y + j.pair), u.y + min(s.y, s.x + j.pair));
        }
    }
    chain_min[j.chain_off + loc * nchains + c] = min(s.x, s.y);
}

@compute @workgroup_size(64, 1, 1)
fn sum_chains(@builtin(global_invocation_id) id: vec3<u32>) {
    let j = jobs[id.z];
    let loc = id.x;
    if (loc >= j.nx * j.ny) {
        return;
    }
    let nchains = j.rows + j.cols;
    let base = j.chain_off + loc * nchains;
    var acc = 0.0;
    for (var c = 0u; c < nchains; c += 1u) {
        acc += chain_min[base + c];
    }
    bounds[j.out_off + loc] = acc;
}
