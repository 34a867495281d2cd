// Area-averaging resize of every pyramid level at once (CPU reference:
// `ColorImage::resize_area` in src/vision/image.rs). Two separable passes,
// horizontal then vertical, with the CPU's own tap tables (input index and
// normalised overlap weight per output coordinate) and the CPU's order of
// summation. Workgroup z is the level (of any image of the batch).

struct Level {
    src_w: u32, src_h: u32, src_off: u32, dst_w: u32,
    dst_h: u32, dst_off: u32, tmp_off: u32, xtap_off: u32,
    ytap_off: u32, cw: u32, ch: u32, hist_off: u32,
    hog_off: u32, grad_off: u32, pad0: u32, pad1: u32,
}

@group(0) @binding(0) var<storage, read> levels: array<Level>;
// Per output coordinate: [start, end) into the tap list (x tables then y
// tables of every level, back to back), then the taps as (index, weight bits).
@group(0) @binding(1) var<storage, read> taps: array<u32>;
@group(0) @binding(2) var<storage, read> src: array<f32>;
@group(0) @binding(3) var<storage, read_write> tmp: array<f32>;
@group(0) @binding(4) var<storage, read_write> dst: array<f32>;

// taps layout at `off`: n+1 offsets (relative to off), then pairs.
fn tap_range(off: u32, o: u32) -> vec2<u32> {
    return vec2<u32>(off + taps[off + o], off + taps[off + o + 1u]);
}

@compute @workgroup_size(8, 8, 1)
fn resize_h(@builtin(global_invocation_id) id: vec3<u32>) {
    let lv = levels[id.z];
    let ox = id.x;
    let y = id.y;
    if (ox >= lv.dst_w || y >= lv.src_h) {
        return;
    }
    let r = tap_range(lv.xtap_off, ox);
    var acc = vec3<f32>(0.0, 0.0, 0.0);
    for (var k = r.x; k < r.y; k += 2u) {
        let ix = taps[k];
        let w = bitcast<f32>(taps[k + 1u]);
        let s = lv.src_off + (y * lv.src_w + ix) * 3u;
        acc.x += w * src[s];
        acc.y += w * src[s + 1u];
        acc.z += w * src[s + 2u];
    }
    let d = lv.tmp_off + (y * lv.dst_w + ox) * 3u;
    tmp[d] = acc.x;
    tmp[d + 1u] = acc.y;
    tmp[d + 2u] = acc.z;
}

@compute @workgroup_size(8, 8, 1)
fn resize_v(@builtin(global_invocation_id) id: vec3<u32>) {
    let lv = levels[id.z];
    let ox = id.x;
    let oy = id.y;
    if (ox >= lv.dst_w || oy >= lv.dst_h) {
        return;
    }
    let r = tap_range(lv.ytap_off, oy);
    var acc = vec3<f32>(0.0, 0.0, 0.0);
    for (var k = r.x; k < r.y; k += 2u) {
        let iy = taps[k];
        let w = bitcast<f32>(taps[k + 1u]);
        let s = lv.tmp_off + (iy * lv.dst_w + ox) * 3u;
        acc.x += w * tmp[s];
        acc.y += w * tmp[s + 1u];
        acc.z += w * tmp[s + 2u];
    }
    let d = lv.dst_off + (oy * lv.dst_w + ox) * 3u;
    dst[d] = acc.x;
    dst[d + 1u] = acc.y;
    dst[d + 2u] = acc.z;
}
