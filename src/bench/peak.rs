//! The machine's FMA peak: independent fused multiply-adds on the widest vectors the core has
//! (512-bit where it has AVX-512F, else 256-bit with FMA), on every thread of the pool at once.
//! "% of peak" in the bench is against this figure, not against one library's GEMM. Also the
//! peaks of the reduced-precision instructions the heads use where the core has them (f16
//! `VFMADD231PH`, bfloat16 `VDPBF16PS`): their rates differ between CPUs more than f32's do.

use std::time::Instant;

use rayon::prelude::*;

/// The widest FMA a probe measured, and its rate over all the pool's threads.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct FmaPeak {
    /// Vector width in bits (512, 256, or 0 where the core has neither).
    pub bits: u32,
    /// GFLOP/s over the pool's threads (an FMA counts two).
    pub gflops: f64,
}

/// Independent accumulators per thread: enough to cover the FMA latency (4 cycles) on two units,
/// and few enough to stay in registers (16 of the 32 zmm; 12 of the 16 ymm, with the two
/// operands).
const CHAINS_512: usize = 16;
const CHAINS_256: usize = 12;

/// Iterations of the inner loop per timed run: ~40–80 ms on one core (a run of 1 s measured
/// the same rate: no clock drop under sustained 512-bit FMAs on the machines seen).
const ITERS: usize = 1 << 23;

/// Rounds of four `TDPBF16PS` per thread in the AMX probe (each about 64 cycles).
const AMX_ROUNDS: usize = 1 << 20;

/// The widest FMA this core has, measured (best of 5 runs on every thread of the pool), or the
/// 256-bit one when `widest` is false.
pub fn fma_peak(widest: bool) -> FmaPeak {
    let bits = fma_bits(widest);
    if bits == 0 {
        return FmaPeak { bits, gflops: 0.0 };
    }
    let chains = if bits == 512 { CHAINS_512 } else { CHAINS_256 };
    let flops_per_run = (ITERS * chains * (bits as usize / 32) * 2) as f64;
    FmaPeak {
        bits,
        gflops: pool_gflops(flops_per_run, |i| fma_chains(bits, 1.0 + i as f32 * 1e-7)),
    }
}

/// GFLOP/s of `run` (thread `i`'s share, `flops_per_run` each) on every thread of the pool at
/// once: the best of 5 timed rounds, after one untimed.
fn pool_gflops(flops_per_run: f64, run: impl Fn(usize) -> f32 + Sync) -> f64 {
    let threads = rayon::current_num_threads();
    let mut best = f64::MAX;
    for _ in 0..6 {
        let t = Instant::now();
        let sum: f32 = (0..threads).into_par_iter().map(&run).sum();
        best = best.min(t.elapsed().as_secs_f64());
        std::hint::black_box(sum);
    }
    flops_per_run * threads as f64 / best / 1e9
}

fn fma_bits(widest: bool) -> u32 {
    #[cfg(target_arch = "x86_64")]
    {
        if widest && std::is_x86_feature_detected!("avx512f") {
            512
        } else if std::is_x86_feature_detected!("avx2") && std::is_x86_feature_detected!("fma") {
            256
        } else {
            0
        }
    }
    #[cfg(not(target_arch = "x86_64"))]
    {
        let _ = widest;
        0
    }
}

/// [`ITERS`] rounds of independent FMAs of `bits`-wide vectors, summed.
fn fma_chains(bits: u32, seed: f32) -> f32 {
    #[cfg(target_arch = "x86_64")]
    // SAFETY: `fma_bits` checked the features of the width asked for.
    unsafe {
        if bits == 512 {
            fma512(seed)
        } else {
            fma256(seed)
        }
    }
    #[cfg(not(target_arch = "x86_64"))]
    {
        let _ = bits;
        seed
    }
}

/// # Safety
/// The core has AVX-512F.
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx512f")]
unsafe fn fma512(seed: f32) -> f32 {
    use std::arch::x86_64::*;
    let a = _mm512_set1_ps(seed);
    let b = _mm512_set1_ps(1e-9);
    let mut acc = [_mm512_set1_ps(0.5); CHAINS_512];
    for _ in 0..ITERS {
        for acc in acc.iter_mut() {
            *acc = _mm512_fmadd_ps(*acc, a, b);
        }
    }
    let mut sum = acc[0];
    for acc in &acc[1..] {
        sum = _mm512_add_ps(sum, *acc);
    }
    _mm512_reduce_add_ps(sum)
}

/// # Safety
/// The core has AVX2 and FMA.
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2,fma")]
unsafe fn fma256(seed: f32) -> f32 {
    use std::arch::x86_64::*;
    let a = _mm256_set1_ps(seed);
    let b = _mm256_set1_ps(1e-9);
    let mut acc = [_mm256_set1_ps(0.5); CHAINS_256];
    for _ in 0..ITERS {
        for acc in acc.iter_mut() {
            *acc = _mm256_fmadd_ps(*acc, a, b);
        }
    }
    let mut sum = acc[0];
    for acc in &acc[1..] {
        sum = _mm256_add_ps(sum, *acc);
    }
    let mut lanes = [0f32; 8];
    // SAFETY: `lanes` holds 8 floats.
    unsafe { _mm256_storeu_ps(lanes.as_mut_ptr(), sum) };
    lanes.iter().sum()
}

/// A reduced-precision instruction the heads use, for [`reduced_peak`].
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum ReducedOp {
    /// `VFMADD231PH` on 512-bit vectors (AVX-512 FP16): 32 multiply-adds.
    F16Fma,
    /// `VDPBF16PS` on 512-bit vectors (AVX-512 BF16): 32 multiply-adds into 16 f32 lanes.
    Bf16Dot,
    /// `VPDPBUSD` on 512-bit vectors (AVX-512 VNNI): 64 byte multiply-adds into 16 i32 lanes
    /// (counted as operations, two per multiply-add, like the floating-point ones).
    I8Dot,
    /// `VPMADDWD` on 256-bit vectors (AVX2) with the `VPADDD` that accumulates it: 16
    /// multiply-adds of 16-bit pairs into 8 i32 lanes, the 8-bit head's kernel on cores without
    /// VNNI (counted as [`ReducedOp::I8Dot`]).
    I8Pairs,
}

/// The rate of `op` over the pool's threads in GFLOP/s (a multiply-add counts two; best of 5
/// runs), or `None` where the core lacks it.
pub fn reduced_peak(op: ReducedOp) -> Option<f64> {
    #[cfg(target_arch = "x86_64")]
    {
        let has = |f: bool| f && std::is_x86_feature_detected!("avx512f");
        let available = match op {
            ReducedOp::F16Fma => has(std::is_x86_feature_detected!("avx512fp16")),
            ReducedOp::Bf16Dot => has(std::is_x86_feature_detected!("avx512bf16")),
            ReducedOp::I8Dot => has(std::is_x86_feature_detected!("avx512vnni")),
            ReducedOp::I8Pairs => std::is_x86_feature_detected!("avx2"),
        };
        if !available {
            return None;
        }
        let (chains, flops) = match op {
            ReducedOp::F16Fma => (CHAINS_F16, 64),
            ReducedOp::Bf16Dot => (CHAINS_512, 64),
            ReducedOp::I8Dot => (CHAINS_512, 128),
            ReducedOp::I8Pairs => (CHAINS_256, 32),
        };
        let flops_per_run = (ITERS * chains * flops) as f64;
        // SAFETY: the features were checked above.
        Some(pool_gflops(flops_per_run, |i| unsafe {
            match op {
                ReducedOp::F16Fma => f16_chains(i as i16),
                ReducedOp::Bf16Dot => bf16_chains(i as i32),
                ReducedOp::I8Dot => i8_chains(i as i32),
                ReducedOp::I8Pairs => i8_pairs_chains(i as i32),
            }
        }))
    }
    #[cfg(not(target_arch = "x86_64"))]
    {
        let _ = op;
        None
    }
}

/// The rate of `TDPBF16PS` on AMX tiles (16 × 16 × 32 multiply-adds into a tile of f32) over
/// the pool's threads in GFLOP/s, or `None` where the core has no AMX granted.
pub fn amx_peak() -> Option<f64> {
    use crate::net::amx::{ROUND_MULTIPLY_ADDS, amx_peak_rounds};
    amx_peak_rounds(1)?;
    let flops_per_run = (AMX_ROUNDS * ROUND_MULTIPLY_ADDS * 2) as f64;
    Some(pool_gflops(flops_per_run, |_| {
        amx_peak_rounds(AMX_ROUNDS).unwrap_or(0.0)
    }))
}

/// The rate of `TDPBUSD` on AMX tiles (16 × 16 × 64 byte multiply-adds into a tile of i32) over
/// the pool's threads in GOP/s, or `None` where the core has no AMX-INT8 granted.
pub fn amx_int8_peak() -> Option<f64> {
    use crate::net::amx::{ROUND_MULTIPLY_ADDS_I8, amx_int8_peak_rounds};
    amx_int8_peak_rounds(1)?;
    let ops_per_run = (AMX_ROUNDS * ROUND_MULTIPLY_ADDS_I8 * 2) as f64;
    Some(pool_gflops(ops_per_run, |_| {
        amx_int8_peak_rounds(AMX_ROUNDS).unwrap_or(0.0)
    }))
}

/// Independent f16 accumulators: LLVM keeps f16 vectors in 16 of the 32 zmm registers and
/// spilled 3 of 16 chains to the stack, which made the probe measure store forwarding.
const CHAINS_F16: usize = 12;

/// [`ITERS`] rounds of [`CHAINS_F16`] independent `VFMADD231PH`.
///
/// # Safety
/// The core has AVX-512F, AVX-512BW and AVX-512 FP16.
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx512f,avx512bw,avx512fp16")]
unsafe fn f16_chains(seed: i16) -> f32 {
    use std::arch::x86_64::*;
    // acc ← acc·a + b with a a little below 1 and b small, as f16 bits: acc settles near
    // b / (1 − a), a normal number (subnormal operands may take a slow path). The seed keeps the
    // threads' work distinct.
    let a = _mm512_castsi512_ph(_mm512_set1_epi16(0x3bf0 - seed));
    let b = _mm512_castsi512_ph(_mm512_set1_epi16(0x1400));
    let mut acc = [_mm512_castsi512_ph(_mm512_set1_epi16(0x3800)); CHAINS_F16];
    for _ in 0..ITERS {
        for acc in acc.iter_mut() {
            *acc = _mm512_fmadd_ph(*acc, a, b);
        }
    }
    let mut sum = _mm512_setzero_ps();
    for acc in &acc {
        let low = _mm512_castsi512_si256(_mm512_castph_si512(*acc));
        sum = _mm512_add_ps(sum, _mm512_cvtxph_ps(_mm256_castsi256_ph(low)));
    }
    _mm512_reduce_add_ps(sum)
}

/// [`ITERS`] rounds of [`CHAINS_512`] independent `VDPBF16PS`.
///
/// # Safety
/// The core has AVX-512F and AVX-512 BF16.
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx512f,avx512bf16")]
unsafe fn bf16_chains(seed: i32) -> f32 {
    use std::arch::x86_64::*;
    // Pairs of bfloat16 0.99 and 1/256 (normal numbers) times pairs of 2⁻³¹.
    // SAFETY: both are 512 bits of plain data.
    let (a, b): (__m512bh, __m512bh) = unsafe {
        (
            std::mem::transmute::<__m512i, __m512bh>(_mm512_set1_epi32(0x3f7d_3b80 + seed)),
            std::mem::transmute::<__m512i, __m512bh>(_mm512_set1_epi32(0x3000_3000)),
        )
    };
    let mut acc = [_mm512_set1_ps(0.5); CHAINS_512];
    for _ in 0..ITERS {
        for acc in acc.iter_mut() {
            *acc = _mm512_dpbf16_ps(*acc, a, b);
        }
    }
    let mut sum = acc[0];
    for acc in &acc[1..] {
        sum = _mm512_add_ps(sum, *acc);
    }
    _mm512_reduce_add_ps(sum)
}

/// [`ITERS`] rounds of [`CHAINS_512`] independent `VPDPBUSD`.
///
/// # Safety
/// The core has AVX-512F and AVX-512 VNNI.
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx512f,avx512vnni")]
unsafe fn i8_chains(seed: i32) -> f32 {
    use std::arch::x86_64::*;
    // Small bytes, so that the i32 sums do not wrap within the probe.
    let (a, b) = (
        _mm512_set1_epi32(0x0102_0301 + seed),
        _mm512_set1_epi32(0x0101_0101),
    );
    let mut acc = [_mm512_setzero_si512(); CHAINS_512];
    for _ in 0..ITERS {
        for acc in acc.iter_mut() {
            *acc = _mm512_dpbusd_epi32(*acc, a, b);
        }
    }
    let mut sum = acc[0];
    for acc in &acc[1..] {
        sum = _mm512_add_epi32(sum, *acc);
    }
    _mm512_reduce_add_epi32(sum) as f32
}

/// [`ITERS`] rounds of [`CHAINS_256`] independent `VPADDD(acc, VPMADDWD(acc, b))`: each product
/// reads its own accumulator, so that none is hoisted out of the loop (the i32 sums wrap, as
/// vector integer sums do).
///
/// # Safety
/// The core has AVX2.
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2")]
unsafe fn i8_pairs_chains(seed: i32) -> f32 {
    use std::arch::x86_64::*;
    let b = _mm256_set1_epi32(0x0001_0003);
    let mut acc = [_mm256_set1_epi32(seed); CHAINS_256];
    for _ in 0..ITERS {
        for acc in acc.iter_mut() {
            *acc = _mm256_add_epi32(*acc, _mm256_madd_epi16(*acc, b));
        }
    }
    let mut sum = acc[0];
    for acc in &acc[1..] {
        sum = _mm256_add_epi32(sum, *acc);
    }
    let mut lanes = [0i32; 8];
    // SAFETY: `lanes` holds 8 i32.
    unsafe { _mm256_storeu_si256(lanes.as_mut_ptr() as *mut __m256i, sum) };
    lanes.iter().fold(0i32, |s, &v| s.wrapping_add(v)) as f32
}
