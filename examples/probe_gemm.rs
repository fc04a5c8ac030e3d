//! Matmul peak of the fused head's library for tiles of 64–512 rows (`bench::matmul_peak_gflops`:
//! a 4096×256 · 256×256 product, one tile per rayon task, matrixmultiply single-threaded inside a
//! tile). With the `gemm` crate 0.19 in the same loop (as a dev-dependency, since removed) this
//! machine measured gemm at 211–241 GFLOP/s and matrixmultiply at 291–369 GFLOP/s, so the fused
//! head uses matrixmultiply with the fastest tile (`net::tiles::TILE_ROWS`).
//! `cargo run --release --example probe_gemm`
fn main() {
    for tile in [64usize, 128, 256, 512] {
        println!(
            "matrixmultiply tile {tile:>3}: {:.1} GFLOP/s",
            alignist::bench::matmul_peak_gflops(tile)
        );
    }
}
