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
                    let h: [__m512; 4] = std::array::from_fn(|c| {
                        _mm512_max_ps(_mm512_add_ps(sums[c], bias[c]), zero)
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
                            dots[row] += super::native::dot4(&h, weights.as_ptr().add(panel * NR));
                        }
                    }
                }
            }
        }
    }
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
            "vpxord zmm0, zmm0, zmm0",
            "vpxord zmm1, zmm1, zmm1",
            "vpxord zmm2, zmm2, zmm2",
            "vpxord zmm3, zmm3, zmm3",
            "vpxord zmm4, zmm4, zmm4",
            "vpxord zmm5, zmm5, zmm5",
            "vpxord zmm6, zmm6, zmm6",
            "vpxord zmm7, zmm7, zmm7",
            "vpxord zmm8, zmm8, zmm8",
            "vpxord zmm9, zmm9, zmm9",
            "vpxord zmm10, zmm10, zmm10",
            "vpxord zmm11, zmm11, zmm11",
            "vpxord zmm12, zmm12, zmm12",
            "vpxord zmm13, zmm13, zmm13",
            "vpxord zmm14, zmm14, zmm14",
            "vpxord zmm15, zmm15, zmm15",
            "vpxord zmm16, zmm16, zmm16",
            "vpxord zmm17, zmm17, zmm17",
            "vpxord zmm18, zmm18, zmm18",
            "vpxord zmm19, zmm19, zmm19",
            "vpxord zmm20, zmm20, zmm20",
            "vpxord zmm21, zmm21, zmm21",
            "vpxord zmm22, zmm22, zmm22",
            "vpxord zmm23, zmm23, zmm23",
            "2:",
            "vmovdqu16 zmm24, [{w}]",
            "vmovdqu16 zmm25, [{w} + 64]",
            "vfmadd231ph zmm0, zmm24, word ptr [{a0}]{{1to32}}",
            "vfmadd231ph zmm1, zmm25, word ptr [{a0}]{{1to32}}",
            "vfmadd231ph zmm2, zmm24, word ptr [{a0} + {s}]{{1to32}}",
            "vfmadd231ph zmm3, zmm25, word ptr [{a0} + {s}]{{1to32}}",
            "vfmadd231ph zmm4, zmm24, word ptr [{a0} + {s}*2]{{1to32}}",
            "vfmadd231ph zmm5, zmm25, word ptr [{a0} + {s}*2]{{1to32}}",
            "vfmadd231ph zmm6, zmm24, word ptr [{a1}]{{1to32}}",
            "vfmadd231ph zmm7, zmm25, word ptr [{a1}]{{1to32}}",
            "vfmadd231ph zmm8, zmm24, word ptr [{a1} + {s}]{{1to32}}",
            "vfmadd231ph zmm9, zmm25, word ptr [{a1} + {s}]{{1to32}}",
            "vfmadd231ph zmm10, zmm24, word ptr [{a1} + {s}*2]{{1to32}}",
            "vfmadd231ph zmm11, zmm25, word ptr [{a1} + {s}*2]{{1to32}}",
            "vfmadd231ph zmm12, zmm24, word ptr [{a2}]{{1to32}}",
            "vfmadd231ph zmm13, zmm25, word ptr [{a2}]{{1to32}}",
            "vfmadd231ph zmm14, zmm24, word ptr [{a2} + {s}]{{1to32}}",
            "vfmadd231ph zmm15, zmm25, word ptr [{a2} + {s}]{{1to32}}",
            "vfmadd231ph zmm16, zmm24, word ptr [{a2} + {s}*2]{{1to32}}",
            "vfmadd231ph zmm17, zmm25, word ptr [{a2} + {s}*2]{{1to32}}",
            "vfmadd231ph zmm18, zmm24, word ptr [{a3}]{{1to32}}",
            "vfmadd231ph zmm19, zmm25, word ptr [{a3}]{{1to32}}",
            "vfmadd231ph zmm20, zmm24, word ptr [{a3} + {s}]{{1to32}}",
            "vfmadd231ph zmm21, zmm25, word ptr [{a3} + {s}]{{1to32}}",
            "vfmadd231ph zmm22, zmm24, word ptr [{a3} + {s}*2]{{1to32}}",
            "vfmadd231ph zmm23, zmm25, word ptr [{a3} + {s}*2]{{1to32}}",
            "add {a0}, 2",
            "add {a1}, 2",
            "add {a2}, 2",
            "add {a3}, 2",
            "add {w}, 128",
            "dec {n}",
            "jnz 2b",
            "vcvtph2psx zmm26, ymm0",
            "vextracti64x4 ymm27, zmm0, 1",
            "vcvtph2psx zmm27, ymm27",
            "vaddps zmm26, zmm26, [{sums} + 0]",
            "vaddps zmm27, zmm27, [{sums} + 64]",
            "vmovups [{sums} + 0], zmm26",
            "vmovups [{sums} + 64], zmm27",
            "vcvtph2psx zmm26, ymm1",
            "vextracti64x4 ymm27, zmm1, 1",
            "vcvtph2psx zmm27, ymm27",
            "vaddps zmm26, zmm26, [{sums} + 128]",
            "vaddps zmm27, zmm27, [{sums} + 192]",
            "vmovups [{sums} + 128], zmm26",
            "vmovups [{sums} + 192], zmm27",
            "vcvtph2psx zmm26, ymm2",
            "vextracti64x4 ymm27, zmm2, 1",
            "vcvtph2psx zmm27, ymm27",
            "vaddps zmm26, zmm26, [{sums} + 256]",
            "vaddps zmm27, zmm27, [{sums} + 320]",
            "vmovups [{sums} + 256], zmm26",
            "vmovups [{sums} + 320], zmm27",
            "vcvtph2psx zmm26, ymm3",
            "vextracti64x4 ymm27, zmm3, 1",
            "vcvtph2psx zmm27, ymm27",
            "vaddps zmm26, zmm26, [{sums} + 384]",
            "vaddps zmm27, zmm27, [{sums} + 448]",
            "vmovups [{sums} + 384], zmm26",
            "vmovups [{sums} + 448], zmm27",
            "vcvtph2psx zmm26, ymm4",
            "vextracti64x4 ymm27, zmm4, 1",
            "vcvtph2psx zmm27, ymm27",
            "vaddps zmm26, zmm26, [{sums} + 512]",
            "vaddps zmm27, zmm27, [{sums} + 576]",
            "vmovups [{sums} + 512], zmm26",
            "vmovups [{sums} + 576], zmm27",
            "vcvtph2psx zmm26, ymm5",
            "vextracti64x4 ymm27, zmm5, 1",
            "vcvtph2psx zmm27, ymm27",
            "vaddps zmm26, zmm26, [{sums} + 640]",
            "vaddps zmm27, zmm27, [{sums} + 704]",
            "vmovups [{sums} + 640], zmm26",
            "vmovups [{sums} + 704], zmm27",
            "vcvtph2psx zmm26, ymm6",
            "vextracti64x4 ymm27, zmm6, 1",
            "vcvtph2psx zmm27, ymm27",
            "vaddps zmm26, zmm26, [{sums} + 768]",
            "vaddps zmm27, zmm27, [{sums} + 832]",
            "vmovups [{sums} + 768], zmm26",
            "vmovups [{sums} + 832], zmm27",
            "vcvtph2psx zmm26, ymm7",
            "vextracti64x4 ymm27, zmm7, 1",
            "vcvtph2psx zmm27, ymm27",
            "vaddps zmm26, zmm26, [{sums} + 896]",
            "vaddps zmm27, zmm27, [{sums} + 960]",
            "vmovups [{sums} + 896], zmm26",
            "vmovups [{sums} + 960], zmm27",
            "vcvtph2psx zmm26, ymm8",
            "vextracti64x4 ymm27, zmm8, 1",
            "vcvtph2psx zmm27, ymm27",
            "vaddps zmm26, zmm26, [{sums} + 1024]",
            "vaddps zmm27, zmm27, [{sums} + 1088]",
            "vmovups [{sums} + 1024], zmm26",
            "vmovups [{sums} + 1088], zmm27",
            "vcvtph2psx zmm26, ymm9",
            "vextracti64x4 ymm27, zmm9, 1",
            "vcvtph2psx zmm27, ymm27",
            "vaddps zmm26, zmm26, [{sums} + 1152]",
            "vaddps zmm27, zmm27, [{sums} + 1216]",
            "vmovups [{sums} + 1152], zmm26",
            "vmovups [{sums} + 1216], zmm27",
            "vcvtph2psx zmm26, ymm10",
            "vextracti64x4 ymm27, zmm10, 1",
            "vcvtph2psx zmm27, ymm27",
            "vaddps zmm26, zmm26, [{sums} + 1280]",
            "vaddps zmm27, zmm27, [{sums} + 1344]",
            "vmovups [{sums} + 1280], zmm26",
            "vmovups [{sums} + 1344], zmm27",
            "vcvtph2psx zmm26, ymm11",
            "vextracti64x4 ymm27, zmm11, 1",
            "vcvtph2psx zmm27, ymm27",
            "vaddps zmm26, zmm26, [{sums} + 1408]",
            "vaddps zmm27, zmm27, [{sums} + 1472]",
            "vmovups [{sums} + 1408], zmm26",
            "vmovups [{sums} + 1472], zmm27",
            "vcvtph2psx zmm26, ymm12",
            "vextracti64x4 ymm27, zmm12, 1",
            "vcvtph2psx zmm27, ymm27",
            "vaddps zmm26, zmm26, [{sums} + 1536]",
            "vaddps zmm27, zmm27, [{sums} + 1600]",
            "vmovups [{sums} + 1536], zmm26",
            "vmovups [{sums} + 1600], zmm27",
            "vcvtph2psx zmm26, ymm13",
            "vextracti64x4 ymm27, zmm13, 1",
            "vcvtph2psx zmm27, ymm27",
            "vaddps zmm26, zmm26, [{sums} + 1664]",
            "vaddps zmm27, zmm27, [{sums} + 1728]",
            "vmovups [{sums} + 1664], zmm26",
            "vmovups [{sums} + 1728], zmm27",
            "vcvtph2psx zmm26, ymm14",
            "vextracti64x4 ymm27, zmm14, 1",
            "vcvtph2psx zmm27, ymm27",
            "vaddps zmm26, zmm26, [{sums} + 1792]",
            "vaddps zmm27, zmm27, [{sums} + 1856]",
            "vmovups [{sums} + 1792], zmm26",
            "vmovups [{sums} + 1856], zmm27",
            "vcvtph2psx zmm26, ymm15",
            "vextracti64x4 ymm27, zmm15, 1",
            "vcvtph2psx zmm27, ymm27",
            "vaddps zmm26, zmm26, [{sums} + 1920]",
            "vaddps zmm27, zmm27, [{sums} + 1984]",
            "vmovups [{sums} + 1920], zmm26",
            "vmovups [{sums} + 1984], zmm27",
            "vcvtph2psx zmm26, ymm16",
            "vextracti64x4 ymm27, zmm16, 1",
            "vcvtph2psx zmm27, ymm27",
            "vaddps zmm26, zmm26, [{sums} + 2048]",
            "vaddps zmm27, zmm27, [{sums} + 2112]",
            "vmovups [{sums} + 2048], zmm26",
            "vmovups [{sums} + 2112], zmm27",
            "vcvtph2psx zmm26, ymm17",
            "vextracti64x4 ymm27, zmm17, 1",
            "vcvtph2psx zmm27, ymm27",
            "vaddps zmm26, zmm26, [{sums} + 2176]",
            "vaddps zmm27, zmm27, [{sums} + 2240]",
            "vmovups [{sums} + 2176], zmm26",
            "vmovups [{sums} + 2240], zmm27",
            "vcvtph2psx zmm26, ymm18",
            "vextracti64x4 ymm27, zmm18, 1",
            "vcvtph2psx zmm27, ymm27",
            "vaddps zmm26, zmm26, [{sums} + 2304]",
            "vaddps zmm27, zmm27, [{sums} + 2368]",
            "vmovups [{sums} + 2304], zmm26",
            "vmovups [{sums} + 2368], zmm27",
            "vcvtph2psx zmm26, ymm19",
            "vextracti64x4 ymm27, zmm19, 1",
            "vcvtph2psx zmm27, ymm27",
            "vaddps zmm26, zmm26, [{sums} + 2432]",
            "vaddps zmm27, zmm27, [{sums} + 2496]",
            "vmovups [{sums} + 2432], zmm26",
            "vmovups [{sums} + 2496], zmm27",
            "vcvtph2psx zmm26, ymm20",
            "vextracti64x4 ymm27, zmm20, 1",
            "vcvtph2psx zmm27, ymm27",
            "vaddps zmm26, zmm26, [{sums} + 2560]",
            "vaddps zmm27, zmm27, [{sums} + 2624]",
            "vmovups [{sums} + 2560], zmm26",
            "vmovups [{sums} + 2624], zmm27",
            "vcvtph2psx zmm26, ymm21",
            "vextracti64x4 ymm27, zmm21, 1",
            "vcvtph2psx zmm27, ymm27",
            "vaddps zmm26, zmm26, [{sums} + 2688]",
            "vaddps zmm27, zmm27, [{sums} + 2752]",
            "vmovups [{sums} + 2688], zmm26",
            "vmovups [{sums} + 2752], zmm27",
            "vcvtph2psx zmm26, ymm22",
            "vextracti64x4 ymm27, zmm22, 1",
            "vcvtph2psx zmm27, ymm27",
            "vaddps zmm26, zmm26, [{sums} + 2816]",
            "vaddps zmm27, zmm27, [{sums} + 2880]",
            "vmovups [{sums} + 2816], zmm26",
            "vmovups [{sums} + 2880], zmm27",
            "vcvtph2psx zmm26, ymm23",
            "vextracti64x4 ymm27, zmm23, 1",
            "vcvtph2psx zmm27, ymm27",
            "vaddps zmm26, zmm26, [{sums} + 2944]",
            "vaddps zmm27, zmm27, [{sums} + 3008]",
            "vmovups [{sums} + 2944], zmm26",
            "vmovups [{sums} + 3008], zmm27",
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
