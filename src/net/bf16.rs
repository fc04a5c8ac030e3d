//! The fused head in bfloat16, for the coarse levels of a search: the same layers as
//! [`super::FusedHead`], with weights and every GEMM's input rounded to bfloat16 (round to nearest even)
//! and f32 accumulation. On a core with AVX-512 BF16 the GEMMs run on `VDPBF16PS` (two
//! multiply-adds per f32 lane, about twice the f32 FMA's rate); elsewhere the same rounding is
//! emulated on the f32 GEMM, so a search ranks the same cells on any machine (up to the order of
//! the f32 sums).
//!
//! The native kernel runs in the driver of [`super::native`]: weights packed once into column
//! panels of [`NR`] columns, `[k-pair][column][2]`, so that one panel (256 inputs × 64 columns ×
//! 2 B = 32 KiB) stays in L1 while the rows of a tile stream past it [`MR`] at a time.

use super::native::{Epilogue, Kernel, Packed, kernel_impl};

/// Rows of the native kernel's register block.
pub const MR: usize = 6;
/// Columns of the native kernel's register block (four 16-lane vectors).
pub const NR: usize = 64;

pub use super::tiles::{from_bf16, round_bf16, to_bf16};

/// Whether this core runs the native kernel.
pub fn native_available() -> bool {
    #[cfg(target_arch = "x86_64")]
    {
        std::is_x86_feature_detected!("avx512f") && std::is_x86_feature_detected!("avx512bf16")
    }
    #[cfg(not(target_arch = "x86_64"))]
    {
        false
    }
}

/// bfloat16 pairs on `VDPBF16PS`.
#[derive(Debug, Clone, Copy)]
pub struct Bf16Kernel;

kernel_impl!(Bf16Kernel, u16, group 2, mr MR, nr NR, available native_available,
    convert to_bf16, gemm gemm_bf16);

/// [`Kernel::gemm`] for bfloat16 pairs.
///
/// # Safety
/// As [`Kernel::gemm`], with AVX-512F and AVX-512 BF16.
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx512f,avx512bf16")]
unsafe fn gemm_bf16(
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
            && stride >= 2 * layer.groups
            && bias.len() >= layer.panels * NR
    );
    let pairs = layer.groups;
    let mut epilogue = epilogue;
    for panel in 0..layer.panels {
        // SAFETY (all pointer reads and writes below): within the bounds stated above.
        unsafe {
            let weights = layer.weight.as_ptr().add(panel * pairs * NR * 2);
            let bias: [__m512; 4] =
                std::array::from_fn(|c| _mm512_loadu_ps(bias.as_ptr().add(panel * NR + 16 * c)));
            for r0 in (0..rows).step_by(MR) {
                let mut acc = [[_mm512_setzero_ps(); 4]; MR];
                let a = input.as_ptr().add(r0 * stride);
                for pair in 0..pairs {
                    let w = weights.add(pair * NR * 2);
                    let b: [__m512bh; 4] = std::array::from_fn(|c| {
                        std::mem::transmute(_mm512_loadu_si512(w.add(32 * c) as *const _))
                    });
                    for (r, acc) in acc.iter_mut().enumerate() {
                        let pair_bits =
                            (a.add(r * stride + 2 * pair) as *const i32).read_unaligned();
                        let x: __m512bh = std::mem::transmute(_mm512_set1_epi32(pair_bits));
                        for c in 0..4 {
                            acc[c] = _mm512_dpbf16_ps(acc[c], x, b[c]);
                        }
                    }
                }
                let zero = _mm512_setzero_ps();
                for (r, acc) in acc.iter().enumerate() {
                    let row = r0 + r;
                    let h: [__m512; 4] = std::array::from_fn(|c| {
                        _mm512_max_ps(_mm512_add_ps(acc[c], bias[c]), zero)
                    });
                    finish_row(&h, row, panel * NR, &mut epilogue);
                }
            }
        }
    }
}

/// Where a block row of a bfloat16 kernel goes: `h` (bias and ReLU applied; `N` vectors, the
/// columns from `column`) stored as bfloat16 in row `row`, or its output dot product added to
/// `dots[row]`. Shared with the AMX kernel's epilogue.
///
/// # Safety
/// The core has AVX-512F and AVX-512 BF16; the epilogue's buffers hold row `row` and columns
/// `column..column + 16 N`.
#[cfg(target_arch = "x86_64")]
#[inline]
#[target_feature(enable = "avx512f,avx512bf16")]
pub(super) unsafe fn finish_row<const N: usize>(
    h: &[std::arch::x86_64::__m512; N],
    row: usize,
    column: usize,
    epilogue: &mut Epilogue<'_, u16>,
) {
    use std::arch::x86_64::*;
    // SAFETY (every store and load): within the bounds of the contract.
    unsafe {
        match epilogue {
            Epilogue::Store { out, stride } => {
                let o = out.as_mut_ptr().add(row * *stride + column);
                for (c, h) in h.iter().enumerate() {
                    let packed: __m256i = std::mem::transmute(_mm512_cvtneps_pbh(*h));
                    _mm256_storeu_si256(o.add(16 * c) as *mut __m256i, packed);
                }
            }
            Epilogue::Dot { weights, dots } => {
                dots[row] += super::native::dot(h, weights.as_ptr().add(column));
            }
        }
    }
}
