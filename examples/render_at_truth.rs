//! Renders a BOP object at its annotated pose beside the photograph, to
//! check the renderer's conventions (axes, colours, shading) against real
//! images: `cargo run --release --example render_at_truth -- DATA OBJ_ID IMAGE_ID OUT.png`.

use std::path::PathBuf;

use nalgebra::Vector3;
use sdhop::pose::geometry::{Intrinsics, Pose};
use sdhop::pose::mesh::Mesh;
use sdhop::pose::render::{render_colours, Lighting};

fn main() -> Result<(), Box<dyn std::error::Error>> {
    let a: Vec<String> = std::env::args().collect();
    let data = PathBuf::from(&a[1]);
    let obj: u32 = a[2].parse()?;
    let im: u32 = a[3].parse()?;
    let scene = data.join("test/000002");
    let gt: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(scene.join("scene_gt.json"))?)?;
    let cam: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(scene.join("scene_camera.json"))?)?;
    let kk: Vec<f64> = serde_json::from_value(cam[im.to_string()]["cam_K"].clone())?;
    let k = Intrinsics {
        fx: kk[0],
        fy: kk[4],
        cx: kk[2],
        cy: kk[5],
    };
    let inst = gt[im.to_string()]
        .as_array()
        .and_then(|l| l.iter().find(|g| g["obj_id"] == obj))
        .ok_or("no such instance")?;
    let r: Vec<f64> = serde_json::from_value(inst["cam_R_m2c"].clone())?;
    let t: Vec<f64> = serde_json::from_value(inst["cam_t_m2c"].clone())?;
    let pose = Pose::from_client(
        [[r[0], r[1], r[2]], [r[3], r[4], r[5]], [r[6], r[7], r[8]]],
        [t[0], t[1], t[2]],
    )?;
    let bytes = std::fs::read(data.join(format!("models/obj_{obj:06}.ply")))?;
    let mesh = Mesh::parse(&bytes)?;
    let colours = Mesh::ply_vertex_colours(&bytes)?;
    let photo = image::open(scene.join(format!("rgb/{im:06}.png")))?.to_rgb8();
    let (w, h) = (photo.width() as usize, photo.height() as usize);
    let light = Lighting {
        light: Vector3::new(0.2, 0.3, 1.0),
        ambient: 0.4,
        gain: [1.0; 3],
    };
    let (rgb, mask) = render_colours(&mesh, colours.as_deref(), &k, &pose, w, h, &light)?;
    let mut out = photo.clone();
    for y in 0..h {
        for x in 0..w {
            if mask.get(x, y) {
                let c = rgb[y * w + x];
                out.put_pixel(
                    x as u32,
                    y as u32,
                    image::Rgb([c[0] as u8, c[1] as u8, c[2] as u8]),
                );
            }
        }
    }
    let (x0, y0, x1, y1) = mask.tight_box().ok_or("not in view")?;
    let m = 30;
    let (cx0, cy0) = (x0.saturating_sub(m) as u32, y0.saturating_sub(m) as u32);
    let (cw, ch) = (
        ((x1 + m).min(w) as u32 - cx0),
        ((y1 + m).min(h) as u32 - cy0),
    );
    let a_crop = image::imageops::crop_imm(&photo, cx0, cy0, cw, ch).to_image();
    let b_crop = image::imageops::crop_imm(&out, cx0, cy0, cw, ch).to_image();
    let mut both = image::RgbImage::new(cw * 2, ch);
    image::imageops::replace(&mut both, &a_crop, 0, 0);
    image::imageops::replace(&mut both, &b_crop, i64::from(cw), 0);
    both.save(&a[4])?;
    Ok(())
}
