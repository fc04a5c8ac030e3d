//! The fused head in IEEE half precision, for the coarse levels of a search on cores where
//! half-precision FMAs are fast: the same layers as [`super::FusedHead`], with weights and every
//! GEMM's input rounded to f16 (11 significant bits, three more than bfloat16). On a core with
//! AVX-512 FP16 (Intel since Sapphire Rapids) the GEMMs run on `VFMADD231PH`: 32 lanes per
//! instruction at the f32 FMA's instruction rate, twice its arithmetic. Those FMAs also sum in
//! f16, so the kernel sums at most [`CHUNK`] products in f16 before it adds them to f32 sums
//! (the relative error of a chunk's sum stays near `√CHUNK · 2⁻¹¹`). Elsewhere the same rounding
//! of weights and inputs is emulated on the f32 GEMM (f32 sums throughout).
//!
//! The native kernel runs in the driver of [`super::native`]: weights packed once into column
//! panels of [`NR`] columns, `[input][column]`, so that one panel (256 inputs × 64 columns ×
//! 2 B = 32 KiB) stays in L1 while a tile's rows stream past it [`MR`] at a time.

use super::native::{Epilogue, Kernel, Packed, kernel_impl};

/// Rows of the native kernel's register block.
pub const MR: usize = 12;
/// Columns of the native kernel's register block (two 32-lane vectors).
pub const NR: usize = 64;
/// Products summed in f16 before they join the f32 sums.
pub const CHUNK: usize = 128;

pub use super::tiles::{from_f16, round_f16, to_f16};

/// Whether this core runs the native kernel.
pub fn native_available() -> bool {
    #[cfg(target_arch = "x86_64")]
    {
        std::is_x86_feature_detected!("avx512f")
            && std::is_x86_feature_detected!("avx512bw")
            && std::is_x86_feature_detected!("avx512fp16")
    }
    #[cfg(not(target_arch = "x86_64"))]
    {
        false
    }
}

/// Half precision on `VFMADD231PH`.
#[derive(Debug, Clone, Copy)]
pub struct F16Kernel;

kernel_impl!(F16Kernel, u16, group 1, mr MR, nr NR, available native_available,
    convert to_f16, gemm gemm_f16, convert_row f16_row);

/// `src` rounded to f16 into `dst`, 16 values per `VCVTPS2PHX` where the core has AVX-512 FP16
/// (the same rounding as [`to_f16`]).
fn f16_row(src: &[f32], dst: &mut [u16]) {
    let n = src.len().min(dst.len());
    let mut done = 0;
    #[cfg(target_arch = "x86_64")]
    if native_available() {
        done = n / 16 * 16;
        // SAFETY: the features were checked; both slices hold `done` values.
        unsafe { f16_row_native(&src[..done], &mut dst[..done]) };
    }
    for (d, &s) in dst[done..n].iter_mut().zip(&src[done..n]) {
        *d = to_f16(s);
    }
}

/// # Safety
/// The core has AVX-512F and AVX-512 FP16; `src.len()` is a multiple of 16 and at most
/// `dst.len()`.
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx512f,avx512bw,avx512fp16")]
unsafe fn f16_row_native(src: &[f32], dst: &mut [u16]) {
    use std::arch::x86_64::*;
    for (s, d) in src.chunks_exact(16).zip(dst.chunks_exact_mut(16)) {
        // SAFETY: 16 floats read, 16 halves written.
        unsafe {
            let half = _mm512_cvtxps_ph(_mm512_loadu_ps(s.as_ptr()));
            _mm256_storeu_si256(d.as_mut_ptr() as *mut __m256i, _mm256_castph_si256(half));
        }
    }
}

/// [`Kernel::gemm`] for half precision: blocks of 12 rows × 64 columns, 24 f16 accumulators
/// added into f32 sums every [`CHUNK`] inputs ([`chunk_f16`]).
///
/// # Safety
/// As [`Kernel::gemm`], with AVX-512F, AVX-512BW and AVX-512 FP16.
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx512f,avx512bw,avx512fp16")]
unsafe fn gemm_f16(
    layer: &Packed<u16>,
    bias: &[f32],
    input: &[u16],
    stride: usize,
    rows: usize,
    epilogue: Epilogue<'_, u16>,
) {
    use std::arch::x86_64::*;
    debug_assert!(
        rows.is_multiple_of(MR)
            && input.len() >= rows * stride
            && stride >= layer.groups
            && bias.len() >= layer.panels * NR
    );
    let k = layer.groups;
    let mut epilogue = epilogue;
    for panel in 0..layer.panels {
        // SAFETY (all pointer reads and writes below): within the bounds stated above.
        unsafe {
            let weights = layer.weight.as_ptr().add(panel * k * NR);
            let bias: [__m512; 4] =
                std::array::from_fn(|c| _mm512_loadu_ps(bias.as_ptr().add(panel * NR + 16 * c)));
            for r0 in (0..rows).step_by(MR) {
                let a = input.as_ptr().add(r0 * stride);
                let mut sums = [[_mm512_setzero_ps(); 4]; MR];
                for start in (0..k).step_by(CHUNK) {
                    let n = CHUNK.min(k - start);
                    chunk_f16(
                        a.add(start),
                        2 * stride,
                        weights.add(start * NR),
                        n,
                        sums.as_mut_ptr() as *mut f32,
                    );
                }
                let zero = _mm512_setzero_ps();
                for (r, sums) in sums.iter().enumerate() {
                    let row = r0 + r;
                    // ReLU with zero first: `VMAXPS` returns its second operand when either
                    // is NaN, so a row whose f16 values overflowed (inf − inf) stays NaN and is
                    // scored again in f32, instead of turning into zeros and a finite, wrong
                    // score.
                    let h: [__m512; 4] = std::array::from_fn(|c| {
                        _mm512_max_ps(zero, _mm512_add_ps(sums[c], bias[c]))
                    });
                    match &mut epilogue {
                        Epilogue::Store { out, stride } => {
                            let o = out.as_mut_ptr().add(row * *stride + panel * NR);
                            for (c, h) in h.iter().enumerate() {
                                let half = _mm256_castph_si256(_mm512_cvtxps_ph(*h));
                                _mm256_storeu_si256(o.add(16 * c) as *mut __m256i, half);
                            }
                        }
                        Epilogue::Dot { weights, dots } => {
                            dots[row] += super::native::dot(&h, weights.as_ptr().add(panel * NR));
                        }
                    }
                }
            }
        }
    }
}

/// Two `VFMADD231PH` of one row: accumulators `zmm$a` and `zmm$b` (columns 0–31, 32–63) += the
/// f16 at `$addr` broadcast from memory × the weights in `zmm24` and `zmm25`.
macro_rules! fma_row {
    ($a:literal, $b:literal, $addr:literal) => {
        concat!(
            "vfmadd231ph zmm",
            $a,
            ", zmm24, word ptr ",
            $addr,
            "{{1to32}}\n",
            "vfmadd231ph zmm",
            $b,
            ", zmm25, word ptr ",
            $addr,
            "{{1to32}}\n"
        )
    };
}

/// The f16 accumulator `zmm$acc` (32 columns) converted to f32 and added to the sums at byte
/// offsets `$low` and `$high` of `{sums}`.
macro_rules! flush {
    ($acc:literal, $low:literal, $high:literal) => {
        concat!(
            "vcvtph2psx zmm26, ymm",
            $acc,
            "\n",
            "vextracti64x4 ymm27, zmm",
            $acc,
            ", 1\n",
            "vcvtph2psx zmm27, ymm27\n",
            "vaddps zmm26, zmm26, [{sums} + ",
            $low,
            "]\n",
            "vaddps zmm27, zmm27, [{sums} + ",
            $high,
            "]\n",
            "vmovups [{sums} + ",
            $low,
            "], zmm26\n",
            "vmovups [{sums} + ",
            $high,
            "], zmm27\n"
        )
    };
}

/// One chunk of a block in f16: `acc[r][j] = Σ_(i<n) a[r][i] · w[i][j]` for the block's 12 rows
/// (rows `stride` bytes apart from `a`) and 64 columns (`w`: `n` rows of 64), summed in 24 f16
/// registers (`VFMADD231PH` with the input broadcast from memory), then added to `sums`
/// (`[row][64]` f32). Written in assembly: the compiler neither kept the 24 accumulators in
/// registers nor folded the 16-bit broadcasts into the FMAs.
///
/// # Safety
/// The core has AVX-512F, AVX-512BW and AVX-512 FP16; `n ≥ 1`; `a` holds 12 rows of `n` values
/// at `stride` bytes, `w` `n × 64` values, `sums` `12 × 64`.
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx512f,avx512bw,avx512fp16")]
unsafe fn chunk_f16(a: *const u16, stride: usize, w: *const u16, n: usize, sums: *mut f32) {
    // SAFETY: the caller's contract bounds every address read or written.
    unsafe {
        std::arch::asm!(
            "vpxord zmm0, zmm0, zmm0\nvpxord zmm1, zmm1, zmm1\nvpxord zmm2, zmm2, zmm2\nvpxord zmm3, zmm3, zmm3",
            "vpxord zmm4, zmm4, zmm4\nvpxord zmm5, zmm5, zmm5\nvpxord zmm6, zmm6, zmm6\nvpxord zmm7, zmm7, zmm7",
            "vpxord zmm8, zmm8, zmm8\nvpxord zmm9, zmm9, zmm9\nvpxord zmm10, zmm10, zmm10\nvpxord zmm11, zmm11, zmm11",
            "vpxord zmm12, zmm12, zmm12\nvpxord zmm13, zmm13, zmm13\nvpxord zmm14, zmm14, zmm14\nvpxord zmm15, zmm15, zmm15",
            "vpxord zmm16, zmm16, zmm16\nvpxord zmm17, zmm17, zmm17\nvpxord zmm18, zmm18, zmm18\nvpxord zmm19, zmm19, zmm19",
            "vpxord zmm20, zmm20, zmm20\nvpxord zmm21, zmm21, zmm21\nvpxord zmm22, zmm22, zmm22\nvpxord zmm23, zmm23, zmm23",
            "2:",
            "vmovdqu16 zmm24, [{w}]",
            "vmovdqu16 zmm25, [{w} + 64]",
            fma_row!("0", "1", "[{a0}]"),
            fma_row!("2", "3", "[{a0} + {s}]"),
            fma_row!("4", "5", "[{a0} + {s}*2]"),
            fma_row!("6", "7", "[{a1}]"),
            fma_row!("8", "9", "[{a1} + {s}]"),
            fma_row!("10", "11", "[{a1} + {s}*2]"),
            fma_row!("12", "13", "[{a2}]"),
            fma_row!("14", "15", "[{a2} + {s}]"),
            fma_row!("16", "17", "[{a2} + {s}*2]"),
            fma_row!("18", "19", "[{a3}]"),
            fma_row!("20", "21", "[{a3} + {s}]"),
            fma_row!("22", "23", "[{a3} + {s}*2]"),
            "add {a0}, 2", "add {a1}, 2", "add {a2}, 2", "add {a3}, 2",
            "add {w}, 128", "dec {n}", "jnz 2b",
            flush!("0", "0", "64"),
            flush!("1", "128", "192"),
            flush!("2", "256", "320"),
            flush!("3", "384", "448"),
            flush!("4", "512", "576"),
            flush!("5", "640", "704"),
            flush!("6", "768", "832"),
            flush!("7", "896", "960"),
            flush!("8", "1024", "1088"),
            flush!("9", "1152", "1216"),
            flush!("10", "1280", "1344"),
            flush!("11", "1408", "1472"),
            flush!("12", "1536", "1600"),
            flush!("13", "1664", "1728"),
            flush!("14", "1792", "1856"),
            flush!("15", "1920", "1984"),
            flush!("16", "2048", "2112"),
            flush!("17", "2176", "2240"),
            flush!("18", "2304", "2368"),
            flush!("19", "2432", "2496"),
            flush!("20", "2560", "2624"),
            flush!("21", "2688", "2752"),
            flush!("22", "2816", "2880"),
            flush!("23", "2944", "3008"),
            a0 = inout(reg) a => _,
            a1 = inout(reg) a.byte_add(3 * stride) => _,
            a2 = inout(reg) a.byte_add(6 * stride) => _,
            a3 = inout(reg) a.byte_add(9 * stride) => _,
            s = in(reg) stride,
            w = inout(reg) w => _,
            n = inout(reg) n => _,
            sums = in(reg) sums,
            out("zmm0") _, out("zmm1") _, out("zmm2") _, out("zmm3") _, out("zmm4") _, out("zmm5") _, out("zmm6") _, out("zmm7") _, out("zmm8") _, out("zmm9") _, out("zmm10") _, out("zmm11") _, out("zmm12") _, out("zmm13") _, out("zmm14") _, out("zmm15") _, out("zmm16") _, out("zmm17") _, out("zmm18") _, out("zmm19") _, out("zmm20") _, out("zmm21") _, out("zmm22") _, out("zmm23") _, out("zmm24") _, out("zmm25") _, out("zmm26") _, out("zmm27") _,
            options(nostack),
        );
    }
}
