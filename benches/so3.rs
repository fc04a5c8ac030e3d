//! SO(3) core figures: level-5 grid build time, `cell_of` lookups per second, cube encodings
//! per second. Run with `cargo bench --bench so3`.

use std::hint::black_box;
use std::time::Instant;

use alignist::encoding::cube_encoding;
use alignist::so3::{GridLevel, haar_rotations};
use rand::SeedableRng;
use rand_chacha::ChaCha8Rng;

fn best_of<T>(runs: usize, mut f: impl FnMut() -> T) -> f64 {
    (0..runs)
        .map(|_| {
            let t = Instant::now();
            black_box(f());
            t.elapsed().as_secs_f64()
        })
        .fold(f64::INFINITY, f64::min)
}

fn main() {
    println!("threads: {}", rayon::current_num_threads());

    let build = best_of(5, || GridLevel::new(5).unwrap().matrices_f32());
    println!(
        "level-5 grid build (2 359 296 rotation matrices): {:.1} ms (best of 5)",
        build * 1e3
    );
    let build6 = best_of(1, || GridLevel::new(6).unwrap().matrices_f32());
    println!(
        "level-6 grid build (18 874 368 rotation matrices): {:.1} ms",
        build6 * 1e3
    );

    let rots = haar_rotations(&mut ChaCha8Rng::seed_from_u64(0), 200_000);
    for level in [2u8, 5] {
        let g = GridLevel::new(level).unwrap();
        let secs = best_of(5, || rots.iter().map(|r| g.cell_of(r)).sum::<u64>());
        println!(
            "cell_of at level {level}: {:.2} M lookups/s (one thread)",
            rots.len() as f64 / secs / 1e6
        );
    }

    let mats = GridLevel::new(4).unwrap().matrices_f32();
    let secs = best_of(5, || cube_encoding(&mats));
    println!(
        "cube_encoding: {:.2} M rotations/s (one thread, {} rotations of level 4)",
        mats.len() as f64 / secs / 1e6,
        mats.len()
    );
}
