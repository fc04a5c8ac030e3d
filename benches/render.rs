//! Renderer speed: a 100 352-triangle sphere at 224×224 and the SYMSOL shapes.
//! Run with `cargo bench --bench render`.

use std::time::Instant;

use alignist::cad::shapes::{ALL_SHAPES, uv_sphere_mesh};
use alignist::cad::{Camera, Mesh, RenderOptions, render};
use alignist::data::symsol_pose;
use alignist::so3::haar_rotations;
use rand::SeedableRng;
use rand_chacha::ChaCha8Rng;

fn time_renders(mesh: &Mesh, size: u32, n: usize) -> (f64, f64) {
    let camera = Camera::square(size);
    let rots = haar_rotations(&mut ChaCha8Rng::seed_from_u64(0), n);
    let mut times: Vec<f64> = rots
        .iter()
        .map(|r| {
            let t = Instant::now();
            std::hint::black_box(render(
                mesh,
                &camera,
                &symsol_pose(*r),
                &RenderOptions::default(),
            ));
            t.elapsed().as_secs_f64() * 1e3
        })
        .collect();
    times.sort_by(f64::total_cmp);
    (times[n / 2], times[n * 99 / 100])
}

fn main() {
    let sphere = uv_sphere_mesh(224, 225);
    let (p50, p99) = time_renders(&sphere, 224, 50);
    println!(
        "render {} triangles at 224x224: p50 {p50:.2} ms, p99 {p99:.2} ms (one thread)",
        sphere.triangles.len()
    );
    for shape in ALL_SHAPES {
        let mesh = shape.mesh();
        let (p50, _) = time_renders(&mesh, 224, 50);
        println!(
            "render {:8} {:6} triangles at 224x224: p50 {p50:.2} ms",
            shape.name(),
            mesh.triangles.len()
        );
    }
}
