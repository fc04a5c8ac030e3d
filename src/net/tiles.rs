//! What every head path shares: the tile the rotations are scored in, the rows a head takes
//! (projections or encodings), the precisions, and their roundings (bfloat16, f16, bytes). Below
//! the heads that use them ([`super::fused`], [`super::native`], [`super::bf16`], [`super::f16`],
//! [`super::i8`]), so no two of those import each other both ways.

use rayon::prelude::*;

/// The most rows of one tile, and its rows where the core's L2 size is unknown: measured fastest
/// among 64–512 (`examples/probe_gemm.rs`) on cores with 1–2 MiB of L2, where a tile's
/// activations (2 × 256 rows × 256 × 4 B = 512 KiB) stay in a core's L2. See [`tile_rows`].
pub const TILE_ROWS: usize = 256;

/// Rows of one tile on this core ([`tile_rows_for`] its L2 size, read once from Linux's sysfs).
pub fn tile_rows() -> usize {
    static ROWS: std::sync::OnceLock<usize> = std::sync::OnceLock::new();
    *ROWS.get_or_init(|| tile_rows_for(l2_cache_bytes()))
}

/// Rows of one tile for a core with `l2` bytes of L2 cache: the most, in powers of two from 64
/// to [`TILE_ROWS`], whose two activation buffers of 256-wide f32 rows (1 KiB a row each) fill
/// at most half of it, so that the weights stay beside them; [`TILE_ROWS`] where `l2` is
/// unknown. 128 rows on AMD Zen 3's 512 KiB: the f32 head at level 3 read 79–86 % of the FMA
/// peak there against 71–82 % with 256 rows and 69–74 % with 512 (`probe_full_grid`, 2026-11-27).
pub fn tile_rows_for(l2: Option<usize>) -> usize {
    let Some(l2) = l2 else {
        return TILE_ROWS;
    };
    let fit = (l2 / 2 / (2 * 1024)).min(TILE_ROWS);
    let mut rows = 64;
    while rows * 2 <= fit {
        rows *= 2;
    }
    rows
}

/// The L2 cache of the first core in bytes, from `/sys/devices/system/cpu/cpu0/cache` (the
/// level-2 entry of type `Unified` or `Data`); `None` where that is not readable.
fn l2_cache_bytes() -> Option<usize> {
    let caches = std::fs::read_dir("/sys/devices/system/cpu/cpu0/cache").ok()?;
    caches.flatten().find_map(|entry| {
        let read = |name: &str| std::fs::read_to_string(entry.path().join(name)).ok();
        let level = read("level")?;
        let kind = read("type")?;
        (level.trim() == "2" && matches!(kind.trim(), "Unified" | "Data"))
            .then(|| cache_size_bytes(&read("size")?))
            .flatten()
    })
}

/// A sysfs cache size (`512K`, `2048K`, `1M`, or bytes) in bytes.
fn cache_size_bytes(size: &str) -> Option<usize> {
    let size = size.trim();
    let (digits, unit) = match size.char_indices().find(|(_, c)| !c.is_ascii_digit()) {
        Some((i, _)) => size.split_at(i),
        None => (size, ""),
    };
    let value: usize = digits.parse().ok()?;
    let scale = match unit {
        "" => 1,
        "K" => 1 << 10,
        "M" => 1 << 20,
        "G" => 1 << 30,
        _ => return None,
    };
    value.checked_mul(scale)
}

/// [`tile_rows`] rounded up to a multiple of a kernel's `mr` rows: the rows of its tiles, so
/// that a full tile is whole register blocks (12-row blocks in 256 rows would compute 264).
pub(super) fn blocked_tile_rows(mr: usize) -> usize {
    tile_rows().div_ceil(mr) * mr
}

/// The arithmetic a head is scored in.
#[derive(Debug, Clone, Copy, PartialEq, Eq, PartialOrd, Ord, Hash, Default)]
pub enum Precision {
    /// f32 throughout: the burn network's scores within 1e-4.
    #[default]
    F32,
    /// bfloat16 weights and GEMM inputs, f32 sums ([`super::fused::ReducedHead`]): about twice the rate where the
    /// core has AVX-512 BF16, scores within about 1 % of the f32 ones.
    Bf16,
    /// IEEE half-precision weights and GEMM inputs ([`super::fused::ReducedHead`]), sums in f32 (in
    /// f16 within chunks of [`super::f16::CHUNK`] products on the native kernel): 1.8–1.9 times
    /// the f32 rate where the core has AVX-512 FP16, scores within about 1 % of the f32 ones.
    F16,
    /// 8-bit integers ([`super::fused::ReducedHead`], [`super::i8`]): weights as signed bytes
    /// with a scale per column, activations as unsigned bytes with a scale per row (ReLU outputs
    /// are never negative), encodings on a fixed grid of [−1, 1]; exact integer sums, f32
    /// epilogues. `VPDPBUSD` where the core has AVX-512 VNNI (or AVX-VNNI, 256-bit): about 3
    /// times the f32 rate, scores within a few % of the f32 ones.
    I8,
}

impl Precision {
    /// The name used by flags and the bench (`f32`, `bf16`, `f16`).
    pub fn name(self) -> &'static str {
        match self {
            Precision::F32 => "f32",
            Precision::Bf16 => "bf16",
            Precision::F16 => "f16",
            Precision::I8 => "i8",
        }
    }
}

impl std::fmt::Display for Precision {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(self.name())
    }
}

impl std::str::FromStr for Precision {
    type Err = String;
    fn from_str(s: &str) -> Result<Self, Self::Err> {
        match s {
            "f32" => Ok(Precision::F32),
            "bf16" => Ok(Precision::Bf16),
            "f16" => Ok(Precision::F16),
            "i8" => Ok(Precision::I8),
            other => Err(format!(
                "unknown precision `{other}` (f32, bf16, f16 or i8)"
            )),
        }
    }
}

/// The branches a head scores a row with: both (`s_θ + s_φ`, the model's log-density), or the
/// shape branch `s_θ` alone, at half the arithmetic, for ranking the cells a coarse-to-fine
/// search refines (`engine::SearchParams::shape_only_to`). A branch left out scores 0.
#[derive(Debug, Clone, Copy, PartialEq, Eq, PartialOrd, Ord, Hash, Default)]
pub enum Branches {
    /// The shape and the feature branch.
    #[default]
    Both,
    /// The shape branch alone (the first of the two).
    Shape,
}

impl Branches {
    /// How many of the branches, counted from the shape branch, are scored.
    pub fn count(self) -> usize {
        match self {
            Branches::Both => 2,
            Branches::Shape => 1,
        }
    }
}

/// The rotations a head scores, as their rotation projections or as their encodings.
#[derive(Debug, Clone, Copy)]
pub enum Rows<'a> {
    /// The rotation half of the first layer, `[n, width]` ([`super::FusedHead::project_rotations`]):
    /// a grid's, computed once.
    Projected(&'a [f32]),
    /// The rotations' encodings, `[n, rotation_dim]`.
    Encoded(&'a [f32]),
}

/// The `branches`' scores of the `given.len() / per_row` rows of `given` (0 for a branch left
/// out), one tile of `tile_rows` rows per task over the cores, each task with its scratch from
/// `init`: `tile(scratch, rows of the tile, outputs of the tile: [shape] or [shape, feature])`. A kernel's heads
/// pass [`TILE_ROWS`] rounded up to their register block ([`blocked_tile_rows`]), so that only
/// the last tile computes padding rows.
pub(super) fn by_tiles<S>(
    given: &[f32],
    per_row: usize,
    tile_rows: usize,
    branches: Branches,
    init: impl Fn() -> S + Send + Sync,
    tile: impl Fn(&mut S, &[f32], &mut [&mut [f32]]) + Send + Sync,
) -> (Vec<f32>, Vec<f32>) {
    let n = given.len() / per_row;
    let (mut shape, mut feature) = (vec![0.0; n], vec![0.0; n]);
    shape
        .par_chunks_mut(tile_rows)
        .zip(feature.par_chunks_mut(tile_rows))
        .zip(given.par_chunks(tile_rows * per_row))
        .for_each_init(init, |scratch, ((shape, feature), given)| {
            let mut out = [shape, feature];
            tile(scratch, given, &mut out[..branches.count()])
        });
    (shape, feature)
}

/// `x` rounded to bfloat16 (round to nearest even, as `VCVTNEPS2BF16`), as its 16 bits.
pub fn to_bf16(x: f32) -> u16 {
    let bits = x.to_bits();
    if x.is_nan() {
        return ((bits >> 16) | 0x40) as u16;
    }
    let round = 0x7fff + ((bits >> 16) & 1);
    (bits.wrapping_add(round) >> 16) as u16
}

/// The f32 of a bfloat16's bits.
pub fn from_bf16(h: u16) -> f32 {
    f32::from_bits((h as u32) << 16)
}

/// `x` rounded to the nearest bfloat16.
pub fn round_bf16(x: f32) -> f32 {
    from_bf16(to_bf16(x))
}

/// `x` rounded to IEEE half precision (round to nearest even, as `VCVTPS2PHX`), as its 16 bits.
pub fn to_f16(x: f32) -> u16 {
    half::f16::from_f32(x).to_bits()
}

/// The f32 of a half-precision value's bits.
pub fn from_f16(h: u16) -> f32 {
    half::f16::from_bits(h).to_f32()
}

/// `x` rounded to the nearest half-precision value.
pub fn round_f16(x: f32) -> f32 {
    from_f16(to_f16(x))
}

/// Encodings (sines and cosines, in [−1, 1]) as 8-bit integers: `e ≈ u / ENCODING_SCALE − 1`.
pub const ENCODING_SCALE: f32 = 127.5;

/// `x` (|x| < 2²²) rounded to the nearest integer, ties to even, as `round_ties_even` but
/// without a library call, so that loops of it are vectorised: adding 1.5·2²³ leaves no bits
/// below the unit, and the addition rounds to nearest even.
#[inline]
fn round_even(x: f32) -> f32 {
    const SHIFT: f32 = 12_582_912.0;
    (x + SHIFT) - SHIFT
}

/// An encoding's value on the 8-bit grid of [−1, 1] ([`ENCODING_SCALE`]), as its integer.
#[inline]
pub fn encoding_to_u8(e: f32) -> u8 {
    round_even((e + 1.0).clamp(0.0, 2.0) * ENCODING_SCALE) as i32 as u8
}

/// An encoding rounded to its 8-bit grid ([`encoding_to_u8`]).
pub fn round_encoding_u8(e: f32) -> f32 {
    encoding_to_u8(e) as f32 / ENCODING_SCALE - 1.0
}

/// A row of non-negative activations as unsigned bytes on a grid of `max / 255` (round to
/// nearest even, saturating), into `dst`; returns the grid's step: 0 for a row of zeros, NaN
/// for one whose maximum is not finite (so its scores are not finite either, and the head's
/// guard scores them again in f32).
#[inline]
pub fn row_to_u8(src: &[f32], dst: &mut [u8]) -> f32 {
    let max = src.iter().fold(0f32, |m, &v| m.max(v));
    if !(max > 0.0 && max.is_finite()) {
        dst.iter_mut().for_each(|d| *d = 0);
        return if max.is_finite() { 0.0 } else { f32::NAN };
    }
    let inverse = 255.0 / max;
    for (d, &s) in dst.iter_mut().zip(src) {
        *d = round_even((s * inverse).clamp(0.0, 255.0)) as i32 as u8;
    }
    max / 255.0
}

/// Rows of `width` non-negative activations rounded to their 8-bit grids ([`row_to_u8`]).
pub fn round_rows_u8(values: &mut [f32], width: usize) {
    let mut bytes = vec![0u8; width];
    for row in values.chunks_exact_mut(width) {
        let step = row_to_u8(row, &mut bytes);
        for (v, &b) in row.iter_mut().zip(&bytes) {
            *v = b as f32 * step;
        }
    }
}

/// A layer's weights (`[input][output]`, row-major) as signed bytes with one scale per output
/// column (`max |w| / 127`, round to nearest even): `(bytes, scales)`.
pub fn columns_to_i8(weight: &[f32], outputs: usize) -> (Vec<i8>, Vec<f32>) {
    let mut max = vec![0f32; outputs];
    for row in weight.chunks_exact(outputs) {
        for (m, &w) in max.iter_mut().zip(row) {
            *m = m.max(w.abs());
        }
    }
    let inverse: Vec<f32> = max
        .iter()
        .map(|&m| if m > 0.0 { 127.0 / m } else { 0.0 })
        .collect();
    let bytes = weight
        .chunks_exact(outputs)
        .flat_map(|row| {
            row.iter()
                .zip(&inverse)
                .map(|(&w, &i)| round_even((w * i).clamp(-127.0, 127.0)) as i8)
        })
        .collect();
    (bytes, max.iter().map(|&m| m / 127.0).collect())
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A tile's activations fill at most half the L2: 64 rows for 256 KiB, 128 for Zen 3's
    /// 512 KiB, 256 (the most) from 1 MiB up, and 256 where the size is unknown.
    #[test]
    fn tiles_fit_half_the_l2() {
        let kib = |k: usize| Some(k << 10);
        assert_eq!(tile_rows_for(kib(256)), 64);
        assert_eq!(tile_rows_for(kib(512)), 128);
        assert_eq!(tile_rows_for(kib(1024)), 256);
        assert_eq!(tile_rows_for(kib(2048)), 256);
        assert_eq!(tile_rows_for(kib(32)), 64);
        assert_eq!(tile_rows_for(None), TILE_ROWS);
        assert_eq!(cache_size_bytes("512K\n"), Some(512 << 10));
        assert_eq!(cache_size_bytes("2M"), Some(2 << 20));
        assert_eq!(cache_size_bytes("1048576"), Some(1 << 20));
        assert_eq!(cache_size_bytes("12 KB"), None);
        assert_eq!(cache_size_bytes(""), None);
        assert!((64..=TILE_ROWS).contains(&tile_rows()));
    }
}
