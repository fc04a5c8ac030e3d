//! The bfloat16 head on AMX tiles (`TDPBF16PS`), where the core has AMX-BF16 and the OS grants
//! the tile state: the same rounded values as [`super::bf16`] (weights and every GEMM's input in
//! bfloat16, f32 accumulation), so it ranks the same cells as the `VDPBF16PS` kernel and the
//! emulation, up to the order of the f32 sums. And the 8-bit head's GEMM on AMX-INT8 tiles
//! (`TDPBUSD`, [`gemm_i8_tiles`]): the bytes of [`super::i8`], exact i32 sums, so it scores
//! what the `VPDPBUSD` kernel scores.
//!
//! One `TDPBF16PS` multiplies a tile of 16 rows × 32 bfloat16 by 32 × 16 and adds into 16 × 16
//! f32: 8 192 multiply-adds, against 32 for one 512-bit `VDPBF16PS`. The kernel runs in the tile
//! driver of [`super::native`] with blocks of [`MR`] = 32 rows × [`NR`] = 32 columns: four
//! accumulator tiles (`tmm0`–`tmm3`), two tiles of activations (`tmm4`, `tmm5`, read straight
//! from the activation rows) and two of weights (`tmm6`, `tmm7`, read straight from the packed
//! panels, whose `[pair][column][2]` layout is the tiles' own). As a block leaves the tiles, bias
//! and ReLU (or the output dot product) run on AVX-512 as in the `VDPBF16PS` kernel.
//!
//! The tile instructions sit behind [`TileUnit`]: [`AmxTiles`] issues them (inline assembly;
//! Rust's AMX intrinsics are not stable), [`EmulatedTiles`] computes what Intel's manual says
//! each one does. The kernel's loop, its pointers and strides are the same for both, so the
//! emulation tests them on any core (`net::amx` tests).

use super::native::{Epilogue, Kernel, Packed, kernel_impl};
use super::tiles::{from_bf16, to_bf16};

/// The kernel's name in logs and the bench.
pub const KERNEL_NAME: &str = "AMX bf16 tiles";
/// The 8-bit kernel's name.
pub const KERNEL_NAME_I8: &str = "AMX int8 tiles";

/// Rows of the kernel's block (two tiles of 16 rows).
pub const MR: usize = 32;
/// Columns of the kernel's block and of a packed panel (two tiles of 16 f32 columns).
pub const NR: usize = 32;
/// Inputs per tile step: a tile row of 64 bytes holds 32 bfloat16.
pub const K_STEP: usize = 32;

/// Rows of every tile.
const TILE_ROWS: usize = 16;
/// Bytes of every tile row.
const TILE_BYTES: usize = 64;

/// The eight tile registers' shape, as `LDTILECFG` reads it: palette 1, every tile 16 rows of
/// 64 bytes.
#[repr(C, align(64))]
struct TileConfig([u8; 64]);

impl TileConfig {
    fn all_full() -> TileConfig {
        let mut c = [0u8; 64];
        c[0] = 1; // palette
        for t in 0..8 {
            c[16 + 2 * t..18 + 2 * t].copy_from_slice(&(TILE_BYTES as u16).to_le_bytes());
            c[48 + t] = TILE_ROWS as u8;
        }
        TileConfig(c)
    }
}

/// The tile instructions the kernel uses, on tiles of 16 rows × 64 bytes. `T`, `C`, `A`, `B`
/// name tile registers (0–7).
pub(super) trait TileUnit {
    /// `LDTILECFG`: every tile 16 rows of 64 bytes.
    ///
    /// # Safety
    /// On the native unit, the core has AMX-TILE and the OS granted the tile state.
    unsafe fn configure(&mut self);
    /// `TILEZERO`.
    ///
    /// # Safety
    /// [`TileUnit::configure`] ran.
    unsafe fn zero<const T: u8>(&mut self);
    /// `TILELOADD`: 16 rows of 64 bytes from `base`, `stride` bytes apart.
    ///
    /// # Safety
    /// [`TileUnit::configure`] ran; the 16 rows are readable.
    unsafe fn load<const T: u8>(&mut self, base: *const u8, stride: usize);
    /// `TDPBF16PS C, A, B`: `C[m][n] += Σ_k A[m][2k]·B[k][2n] + A[m][2k+1]·B[k][2n+1]`.
    ///
    /// # Safety
    /// [`TileUnit::configure`] ran.
    unsafe fn dot<const C: u8, const A: u8, const B: u8>(&mut self);
    /// `TDPBUSD C, A, B`: `C[m][n] += Σ_k Σ_t u8(A[m][4k+t])·i8(B[k][4n+t])` in i32.
    ///
    /// # Safety
    /// [`TileUnit::configure`] ran.
    unsafe fn dot_bytes<const C: u8, const A: u8, const B: u8>(&mut self);
    /// `TILESTORED`: 16 rows of 64 bytes to `base`, `stride` bytes apart.
    ///
    /// # Safety
    /// [`TileUnit::configure`] ran; the 16 rows are writable.
    unsafe fn store<const T: u8>(&mut self, base: *mut u8, stride: usize);
    /// `TILERELEASE`.
    ///
    /// # Safety
    /// [`TileUnit::configure`] ran.
    unsafe fn release(&mut self);
}

/// The core's AMX tiles.
pub(super) struct AmxTiles;

#[cfg(target_arch = "x86_64")]
impl TileUnit for AmxTiles {
    #[inline(always)]
    unsafe fn configure(&mut self) {
        let config = TileConfig::all_full();
        // SAFETY: the caller's contract; `config` is 64 aligned bytes.
        unsafe {
            std::arch::asm!("ldtilecfg [{c}]", c = in(reg) config.0.as_ptr(),
                options(nostack, readonly));
        }
    }

    #[inline(always)]
    unsafe fn zero<const T: u8>(&mut self) {
        // SAFETY: the caller's contract.
        unsafe { std::arch::asm!("tilezero tmm{t}", t = const T, options(nostack, nomem)) };
    }

    #[inline(always)]
    unsafe fn load<const T: u8>(&mut self, base: *const u8, stride: usize) {
        // SAFETY: the caller's contract.
        unsafe {
            std::arch::asm!("tileloadd tmm{t}, [{b} + {s} * 1]", t = const T, b = in(reg) base,
                s = in(reg) stride, options(nostack, readonly));
        }
    }

    #[inline(always)]
    unsafe fn dot<const C: u8, const A: u8, const B: u8>(&mut self) {
        // SAFETY: the caller's contract.
        unsafe {
            std::arch::asm!("tdpbf16ps tmm{c}, tmm{a}, tmm{b}", c = const C, a = const A,
                b = const B, options(nostack, nomem));
        }
    }

    #[inline(always)]
    unsafe fn dot_bytes<const C: u8, const A: u8, const B: u8>(&mut self) {
        // SAFETY: the caller's contract.
        unsafe {
            std::arch::asm!("tdpbusd tmm{c}, tmm{a}, tmm{b}", c = const C, a = const A,
                b = const B, options(nostack, nomem));
        }
    }

    #[inline(always)]
    unsafe fn store<const T: u8>(&mut self, base: *mut u8, stride: usize) {
        // SAFETY: the caller's contract.
        unsafe {
            std::arch::asm!("tilestored [{b} + {s} * 1], tmm{t}", t = const T, b = in(reg) base,
                s = in(reg) stride, options(nostack));
        }
    }

    #[inline(always)]
    unsafe fn release(&mut self) {
        // SAFETY: the caller's contract.
        unsafe { std::arch::asm!("tilerelease", options(nostack, nomem)) };
    }
}

#[cfg(not(target_arch = "x86_64"))]
impl TileUnit for AmxTiles {
    unsafe fn configure(&mut self) {
        unreachable!("AMX is only built on x86_64")
    }
    unsafe fn zero<const T: u8>(&mut self) {}
    unsafe fn load<const T: u8>(&mut self, _: *const u8, _: usize) {}
    unsafe fn dot<const C: u8, const A: u8, const B: u8>(&mut self) {}
    unsafe fn dot_bytes<const C: u8, const A: u8, const B: u8>(&mut self) {}
    unsafe fn store<const T: u8>(&mut self, _: *mut u8, _: usize) {}
    unsafe fn release(&mut self) {}
}

/// Eight tiles in memory and the instructions as Intel's manual defines them (products and sums
/// in f32, the two products of a pair added one after the other).
pub(super) struct EmulatedTiles {
    tiles: [[[u8; TILE_BYTES]; TILE_ROWS]; 8],
    configured: bool,
}

impl EmulatedTiles {
    pub(super) fn new() -> EmulatedTiles {
        EmulatedTiles {
            tiles: [[[0; TILE_BYTES]; TILE_ROWS]; 8],
            configured: false,
        }
    }

    fn tile(&mut self, t: u8) -> &mut [[u8; TILE_BYTES]; TILE_ROWS] {
        assert!(self.configured, "a tile instruction before LDTILECFG");
        &mut self.tiles[t as usize]
    }
}

impl TileUnit for EmulatedTiles {
    unsafe fn configure(&mut self) {
        self.configured = true;
    }

    unsafe fn zero<const T: u8>(&mut self) {
        *self.tile(T) = [[0; TILE_BYTES]; TILE_ROWS];
    }

    unsafe fn load<const T: u8>(&mut self, base: *const u8, stride: usize) {
        for (r, row) in self.tile(T).iter_mut().enumerate() {
            // SAFETY: the caller's contract: the 16 rows are readable.
            unsafe { std::ptr::copy_nonoverlapping(base.add(r * stride), row.as_mut_ptr(), 64) };
        }
    }

    unsafe fn dot<const C: u8, const A: u8, const B: u8>(&mut self) {
        assert!(
            C != A && C != B && A != B,
            "TDPBF16PS takes three distinct tiles"
        );
        let (a, b) = (*self.tile(A), *self.tile(B));
        let bf16 = |row: &[u8; TILE_BYTES], i: usize| {
            from_bf16(u16::from_le_bytes([row[2 * i], row[2 * i + 1]]))
        };
        for (m, c_row) in self.tile(C).iter_mut().enumerate() {
            for n in 0..TILE_BYTES / 4 {
                let cell = &mut c_row[4 * n..4 * n + 4];
                let mut acc = f32::from_le_bytes(cell.try_into().expect("4 bytes"));
                for (k, b_row) in b.iter().enumerate() {
                    acc += bf16(&a[m], 2 * k) * bf16(b_row, 2 * n);
                    acc += bf16(&a[m], 2 * k + 1) * bf16(b_row, 2 * n + 1);
                }
                cell.copy_from_slice(&acc.to_le_bytes());
            }
        }
    }

    unsafe fn dot_bytes<const C: u8, const A: u8, const B: u8>(&mut self) {
        assert!(
            C != A && C != B && A != B,
            "TDPBUSD takes three distinct tiles"
        );
        let (a, b) = (*self.tile(A), *self.tile(B));
        for (m, c_row) in self.tile(C).iter_mut().enumerate() {
            for n in 0..TILE_BYTES / 4 {
                let cell = &mut c_row[4 * n..4 * n + 4];
                let mut acc = i32::from_le_bytes(cell.try_into().expect("4 bytes"));
                for (k, b_row) in b.iter().enumerate() {
                    for t in 0..4 {
                        acc = acc
                            .wrapping_add(a[m][4 * k + t] as i32 * b_row[4 * n + t] as i8 as i32);
                    }
                }
                cell.copy_from_slice(&acc.to_le_bytes());
            }
        }
    }

    unsafe fn store<const T: u8>(&mut self, base: *mut u8, stride: usize) {
        for (r, row) in self.tile(T).iter().enumerate() {
            // SAFETY: the caller's contract: the 16 rows are writable.
            unsafe { std::ptr::copy_nonoverlapping(row.as_ptr(), base.add(r * stride), 64) };
        }
    }

    unsafe fn release(&mut self) {
        self.configured = false;
    }
}

/// A block of [`MR`] × [`NR`] sums as the tiles leave it, row-major.
type Block = [f32; MR * NR];

/// Bias, ReLU and the epilogue of one block: `(block, bias, panel, first row, epilogue)`.
type Finish = unsafe fn(&Block, &[f32], usize, usize, &mut Epilogue<'_, u16>);

/// `relu(input · W + bias)` of `rows` rows on `tiles`, block by block through `finish` (bias,
/// ReLU and the epilogue of one block).
///
/// # Safety
/// As [`Kernel::gemm`] for [`AmxBf16`] (`layer.groups` a multiple of 16, `rows` of [`MR`]), and
/// `tiles` may run (see [`TileUnit`]).
unsafe fn gemm_tiles<T: TileUnit>(
    (tiles, finish): (&mut T, Finish),
    layer: &Packed<u16>,
    bias: &[f32],
    input: &[u16],
    stride: usize,
    rows: usize,
    mut epilogue: Epilogue<'_, u16>,
) {
    let pairs = layer.groups;
    assert!(
        rows.is_multiple_of(MR)
            && pairs.is_multiple_of(K_STEP / 2)
            && input.len() >= rows * stride
            && stride >= 2 * pairs
            && bias.len() >= layer.panels * NR
            && layer.weight.len() >= layer.panels * pairs * NR * 2,
        "the AMX kernel's shapes"
    );
    let steps = pairs / (K_STEP / 2);
    let mut block: Block = [0.0; MR * NR];
    let out = block.as_mut_ptr() as *mut u8;
    let (a_stride, b_stride) = (2 * stride, 4 * NR);
    // SAFETY (every tile load and store below): the A tiles read rows r0..r0 + 32 of `input`,
    // inputs 32s..32s + 32 < 2·pairs ≤ stride; the B tiles read pairs 16s..16s + 16 of the
    // panel, columns 0..32; the C tiles write the 32 × 32 block.
    unsafe {
        tiles.configure();
        for panel in 0..layer.panels {
            let weights = layer.weight.as_ptr().add(panel * pairs * NR * 2) as *const u8;
            for r0 in (0..rows).step_by(MR) {
                let a = input.as_ptr().add(r0 * stride) as *const u8;
                tile_block::<_, false>(tiles, (a, a_stride), (weights, b_stride), steps, out);
                finish(&block, bias, panel, r0, &mut epilogue);
            }
        }
        tiles.release();
    }
}

/// One block of [`MR`] × [`NR`] sums into `out` (row-major, 4 bytes a sum): `steps` steps of
/// two A tiles (16 rows each, from `a` with its row stride) times two B tiles (16 columns each,
/// 64 bytes apart, from `b` with its stride, the next step's 16 tile rows further), four
/// accumulators; `TDPBF16PS`, or with `BYTES` `TDPBUSD`.
///
/// # Safety
/// The tiles are configured; every A and B tile of the `steps` and the 32 rows of 128 bytes at
/// `out` are in bounds.
#[inline(always)]
unsafe fn tile_block<T: TileUnit, const BYTES: bool>(
    tiles: &mut T,
    (a, a_stride): (*const u8, usize),
    (b, b_stride): (*const u8, usize),
    steps: usize,
    out: *mut u8,
) {
    let c_stride = 4 * NR;
    // SAFETY: the caller's contract.
    unsafe {
        tiles.zero::<0>();
        tiles.zero::<1>();
        tiles.zero::<2>();
        tiles.zero::<3>();
        for s in 0..steps {
            let a = a.add(s * TILE_BYTES);
            let b = b.add(s * TILE_ROWS * b_stride);
            tiles.load::<4>(a, a_stride);
            tiles.load::<5>(a.add(TILE_ROWS * a_stride), a_stride);
            tiles.load::<6>(b, b_stride);
            tiles.load::<7>(b.add(TILE_BYTES), b_stride);
            four_dots::<_, BYTES>(tiles);
        }
        tiles.store::<0>(out, c_stride);
        tiles.store::<1>(out.add(TILE_BYTES), c_stride);
        tiles.store::<2>(out.add(TILE_ROWS * c_stride), c_stride);
        tiles.store::<3>(out.add(TILE_ROWS * c_stride + TILE_BYTES), c_stride);
    }
}

/// The four products of a step: accumulators 0–3 += A tiles 4, 5 × B tiles 6, 7 (`TDPBF16PS`,
/// or with `BYTES` `TDPBUSD`).
///
/// # Safety
/// The tiles are configured.
#[inline(always)]
unsafe fn four_dots<T: TileUnit, const BYTES: bool>(tiles: &mut T) {
    // SAFETY: the caller's contract.
    unsafe {
        if BYTES {
            tiles.dot_bytes::<0, 4, 6>();
            tiles.dot_bytes::<1, 4, 7>();
            tiles.dot_bytes::<2, 5, 6>();
            tiles.dot_bytes::<3, 5, 7>();
        } else {
            tiles.dot::<0, 4, 6>();
            tiles.dot::<1, 4, 7>();
            tiles.dot::<2, 5, 6>();
            tiles.dot::<3, 5, 7>();
        }
    }
}

/// Bias, ReLU and the epilogue of one block (rows `r0..r0 + MR`, columns of `panel`), per value.
///
/// # Safety
/// The epilogue's buffers hold the block's rows and columns.
unsafe fn finish_scalar(
    block: &Block,
    bias: &[f32],
    panel: usize,
    r0: usize,
    epilogue: &mut Epilogue<'_, u16>,
) {
    for (r, sums) in block.chunks_exact(NR).enumerate() {
        let row = r0 + r;
        let h = sums
            .iter()
            .zip(&bias[panel * NR..])
            .map(|(s, b)| (s + b).max(0.0));
        match epilogue {
            Epilogue::Store { out, stride } => {
                let o = &mut out[row * *stride + panel * NR..][..NR];
                for (o, h) in o.iter_mut().zip(h) {
                    *o = to_bf16(h);
                }
            }
            Epilogue::Dot { weights, dots } => {
                dots[row] += h
                    .zip(&weights[panel * NR..])
                    .map(|(h, w)| h * w)
                    .sum::<f32>();
            }
        }
    }
}

/// [`finish_scalar`] on AVX-512 (`VCVTNEPS2BF16` rounds as [`to_bf16`]).
///
/// # Safety
/// As [`finish_scalar`], and the core has AVX-512F and AVX-512 BF16.
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx512f,avx512bf16")]
unsafe fn finish_avx512(
    block: &Block,
    bias: &[f32],
    panel: usize,
    r0: usize,
    epilogue: &mut Epilogue<'_, u16>,
) {
    use std::arch::x86_64::*;
    // SAFETY (every load and store): the block's rows and the panel's columns are in bounds.
    unsafe {
        let bias: [__m512; 2] =
            std::array::from_fn(|c| _mm512_loadu_ps(bias.as_ptr().add(panel * NR + 16 * c)));
        let zero = _mm512_setzero_ps();
        for r in 0..MR {
            let row = r0 + r;
            let h: [__m512; 2] = std::array::from_fn(|c| {
                let s = _mm512_loadu_ps(block.as_ptr().add(r * NR + 16 * c));
                _mm512_max_ps(_mm512_add_ps(s, bias[c]), zero)
            });
            super::bf16::finish_row(&h, row, panel * NR, epilogue);
        }
    }
}

/// Columns of a packed panel of the 8-bit head ([`super::i8::NR`]): the tiles take it in two
/// blocks of [`NR`].
pub(super) const I8_PANEL: usize = 64;

/// A block of [`MR`] × [`NR`] integer sums as the tiles leave it, row-major.
type BytesBlock = [i32; MR * NR];

/// What an 8-bit layer's epilogue needs besides the sums: every column's bias and scale, the
/// input rows' scales.
#[derive(Clone, Copy)]
pub(super) struct BytesScales<'a> {
    /// `[panels × 64]`.
    pub(super) bias: &'a [f32],
    /// `[panels × 64]`: a weight byte times its column's scale is the weight.
    pub(super) columns: &'a [f32],
    /// One per input row: an activation byte times its row's scale is the activation.
    pub(super) rows: &'a [f32],
}

/// `relu(acc · s_row · s_col + b)` of one block (rows `r0..r0 + MR`, columns `column..column +
/// NR`) into the epilogue: `(block, scales, column, first row, epilogue)`.
type FinishBytes = unsafe fn(&BytesBlock, BytesScales<'_>, usize, usize, &mut Epilogue<'_, f32>);

/// The 8-bit head's GEMM on `tiles` (`TDPBUSD`): `rows` rows of activation bytes (`stride`
/// bytes apart) times `layer` (packed `[panel][group][64][4]` as [`super::i8`] packs it), each
/// block of 32 × 32 sums leaving the tiles through `finish` as `relu(acc · s_row · s_col + b)`.
/// The B tiles are read straight from the packed panels: a group's row of 64 columns × 4 bytes
/// is 256 bytes, 16 of its columns one tile row of 64.
///
/// # Safety
/// `tiles` may run (see [`TileUnit`]); `rows` is a multiple of [`MR`], `layer.groups` of 16;
/// `input` holds `rows × stride` bytes with `stride ≥ 4 × groups`; `scales` hold the layer's
/// `panels × 64` columns and `rows` rows; a `Store` output holds `rows` rows of its stride (≥
/// `panels × 64`), a `Dot` `rows` dots and `panels × 64` weights.
pub(super) unsafe fn gemm_i8_tiles<T: TileUnit>(
    (tiles, finish): (&mut T, FinishBytes),
    layer: &Packed<u8>,
    scales: BytesScales<'_>,
    (input, stride): (&[u8], usize),
    rows: usize,
    mut epilogue: Epilogue<'_, f32>,
) {
    const GROUP: usize = 4;
    let groups = layer.groups;
    let panel_row = I8_PANEL * GROUP;
    assert!(
        rows.is_multiple_of(MR)
            && groups.is_multiple_of(TILE_BYTES / GROUP)
            && input.len() >= rows * stride
            && stride >= GROUP * groups
            && scales.bias.len() >= layer.panels * I8_PANEL
            && scales.columns.len() >= layer.panels * I8_PANEL
            && scales.rows.len() >= rows
            && layer.weight.len() >= layer.panels * groups * panel_row,
        "the AMX int8 kernel's shapes"
    );
    let steps = groups / (TILE_BYTES / GROUP);
    let mut block: BytesBlock = [0; MR * NR];
    let out = block.as_mut_ptr() as *mut u8;
    // SAFETY (every tile load and store below): the A tiles read rows r0..r0 + 32 of `input`,
    // bytes 64s..64s + 64 ≤ 4·groups ≤ stride; the B tiles read groups 16s..16s + 16 of the
    // panel, bytes 4·(32h)..4·(32h + 32) of each group's 256; the C tiles write the 32 × 32 block.
    unsafe {
        tiles.configure();
        for panel in 0..layer.panels {
            let weights = layer.weight.as_ptr().add(panel * groups * panel_row);
            for half in 0..I8_PANEL / NR {
                let column = panel * I8_PANEL + half * NR;
                let weights = weights.add(half * NR * GROUP);
                for r0 in (0..rows).step_by(MR) {
                    let a = (input.as_ptr().add(r0 * stride), stride);
                    tile_block::<_, true>(tiles, a, (weights, panel_row), steps, out);
                    finish(&block, scales, column, r0, &mut epilogue);
                }
            }
        }
        tiles.release();
    }
}

/// The epilogue of one block of integer sums, per value (`mul_add` as the vector kernels' FMA).
///
/// # Safety
/// The epilogue's buffers hold the block's rows and columns.
unsafe fn finish_bytes_scalar(
    block: &BytesBlock,
    scales: BytesScales<'_>,
    column: usize,
    r0: usize,
    epilogue: &mut Epilogue<'_, f32>,
) {
    for (r, sums) in block.chunks_exact(NR).enumerate() {
        let (row, s) = (r0 + r, scales.rows[r0 + r]);
        let h = sums
            .iter()
            .zip(&scales.columns[column..column + NR])
            .zip(&scales.bias[column..column + NR])
            .map(|((&acc, &c), &b)| (acc as f32).mul_add(c * s, b).max(0.0));
        match epilogue {
            Epilogue::Store { out, stride } => {
                for (o, h) in out[row * *stride + column..][..NR].iter_mut().zip(h) {
                    *o = h;
                }
            }
            Epilogue::Dot { weights, dots } => {
                dots[row] += h.zip(&weights[column..]).map(|(h, w)| h * w).sum::<f32>();
            }
        }
    }
}

/// [`finish_bytes_scalar`] on AVX-512, as the `VPDPBUSD` kernel's epilogue computes it.
///
/// # Safety
/// As [`finish_bytes_scalar`], and the core has AVX-512F.
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx512f")]
unsafe fn finish_bytes_avx512(
    block: &BytesBlock,
    scales: BytesScales<'_>,
    column: usize,
    r0: usize,
    epilogue: &mut Epilogue<'_, f32>,
) {
    use std::arch::x86_64::*;
    // SAFETY (every load and store): the block's rows and columns are in bounds.
    unsafe {
        let at = |v: &[f32], c: usize| _mm512_loadu_ps(v.as_ptr().add(column + 16 * c));
        let bias: [__m512; 2] = std::array::from_fn(|c| at(scales.bias, c));
        let columns: [__m512; 2] = std::array::from_fn(|c| at(scales.columns, c));
        let zero = _mm512_setzero_ps();
        for r in 0..MR {
            let row = r0 + r;
            let s = _mm512_set1_ps(scales.rows[row]);
            let h: [__m512; 2] = std::array::from_fn(|c| {
                let acc = _mm512_loadu_si512(block.as_ptr().add(r * NR + 16 * c) as *const _);
                let scaled = _mm512_fmadd_ps(
                    _mm512_cvtepi32_ps(acc),
                    _mm512_mul_ps(columns[c], s),
                    bias[c],
                );
                _mm512_max_ps(scaled, zero)
            });
            match epilogue {
                Epilogue::Store { out, stride } => {
                    let o = out.as_mut_ptr().add(row * *stride + column);
                    _mm512_storeu_ps(o, h[0]);
                    _mm512_storeu_ps(o.add(16), h[1]);
                }
                Epilogue::Dot { weights, dots } => {
                    let w = weights.as_ptr().add(column);
                    let sum = _mm512_mul_ps(h[0], _mm512_loadu_ps(w));
                    let sum = _mm512_fmadd_ps(h[1], _mm512_loadu_ps(w.add(16)), sum);
                    dots[row] += _mm512_reduce_add_ps(sum);
                }
            }
        }
    }
}

/// [`gemm_i8_tiles`] on the core's tiles.
///
/// # Safety
/// As [`gemm_i8_tiles`], and [`amx_int8_available`] holds.
#[cfg(target_arch = "x86_64")]
pub(super) unsafe fn gemm_i8_amx(
    layer: &Packed<u8>,
    scales: BytesScales<'_>,
    input: (&[u8], usize),
    rows: usize,
    epilogue: Epilogue<'_, f32>,
) {
    // SAFETY: the caller's contract; AMX-INT8 cores have AVX-512F (checked with it).
    unsafe {
        gemm_i8_tiles(
            (&mut AmxTiles, finish_bytes_avx512),
            layer,
            scales,
            input,
            rows,
            epilogue,
        )
    }
}

/// [`gemm_i8_tiles`] on [`EmulatedTiles`] (its epilogue on AVX-512 where the core has it): on
/// any core, for the tests.
///
/// # Safety
/// As [`gemm_i8_tiles`].
pub(super) unsafe fn gemm_i8_emulated(
    layer: &Packed<u8>,
    scales: BytesScales<'_>,
    input: (&[u8], usize),
    rows: usize,
    epilogue: Epilogue<'_, f32>,
) {
    #[cfg(target_arch = "x86_64")]
    let finish: FinishBytes = if std::is_x86_feature_detected!("avx512f") {
        finish_bytes_avx512
    } else {
        finish_bytes_scalar
    };
    #[cfg(not(target_arch = "x86_64"))]
    let finish: FinishBytes = finish_bytes_scalar;
    // SAFETY: the caller's contract; `finish_bytes_avx512` only where the core has it.
    unsafe {
        gemm_i8_tiles(
            (&mut EmulatedTiles::new(), finish),
            layer,
            scales,
            input,
            rows,
            epilogue,
        )
    }
}

/// Multiply-adds of one round of [`amx_peak_rounds`]: four `TDPBF16PS` of 16 × 16 × 32.
pub const ROUND_MULTIPLY_ADDS: usize = 4 * TILE_ROWS * TILE_ROWS * K_STEP;

/// Multiply-adds of one round of [`amx_int8_peak_rounds`]: four `TDPBUSD` of 16 × 16 × 64.
pub const ROUND_MULTIPLY_ADDS_I8: usize = 4 * TILE_ROWS * TILE_ROWS * TILE_BYTES;

/// `rounds` rounds of four independent `TDPBF16PS` on tiles loaded once (the bench's AMX peak
/// probe), or `None` where the core has no AMX-BF16 granted. Returns a value of the result,
/// which the caller keeps from being optimised away.
pub fn amx_peak_rounds(rounds: usize) -> Option<f32> {
    // SAFETY: the tiles run only where AMX is granted.
    native_available().then(|| unsafe { tile_rounds::<_, false>(&mut AmxTiles, rounds) })
}

/// The same with `TDPBUSD` (bytes into i32), or `None` where the core has no AMX-INT8 granted.
pub fn amx_int8_peak_rounds(rounds: usize) -> Option<f32> {
    // SAFETY: the tiles run only where AMX-INT8 is granted.
    amx_int8_available().then(|| unsafe { tile_rounds::<_, true>(&mut AmxTiles, rounds) })
}

/// The loop of the peak probes on `tiles`: `TDPBF16PS` with A = 1, B = 2⁻¹⁰ (no sum overflows),
/// or with `BYTES` `TDPBUSD` with A = B = 1 (each round adds 64 to every i32 sum).
///
/// # Safety
/// `tiles` may run (see [`TileUnit`]).
unsafe fn tile_rounds<T: TileUnit, const BYTES: bool>(tiles: &mut T, rounds: usize) -> f32 {
    let (a, b) = if BYTES {
        (
            [0x0101u16; TILE_ROWS * K_STEP],
            [0x0101u16; TILE_ROWS * K_STEP],
        )
    } else {
        (
            [to_bf16(1.0); TILE_ROWS * K_STEP],
            [to_bf16(1.0 / 1024.0); TILE_ROWS * K_STEP],
        )
    };
    let mut c = [0f32; TILE_ROWS * TILE_ROWS];
    let (a, b) = (a.as_ptr() as *const u8, b.as_ptr() as *const u8);
    // SAFETY: every tile reads or writes one of the 16 × 64-byte buffers above.
    unsafe {
        tiles.configure();
        tiles.zero::<0>();
        tiles.zero::<1>();
        tiles.zero::<2>();
        tiles.zero::<3>();
        tiles.load::<4>(a, TILE_BYTES);
        tiles.load::<5>(a, TILE_BYTES);
        tiles.load::<6>(b, TILE_BYTES);
        tiles.load::<7>(b, TILE_BYTES);
        for _ in 0..rounds {
            four_dots::<_, BYTES>(tiles);
        }
        tiles.store::<3>(c.as_mut_ptr() as *mut u8, TILE_BYTES);
        tiles.release();
    }
    if BYTES {
        c[0].to_bits() as i32 as f32
    } else {
        c[0]
    }
}

/// Whether the core has AMX-TILE and AMX-BF16 and the OS saves their state (CPUID and XCR0), and
/// on Linux, whether it granted this process the tile data (`arch_prctl(ARCH_REQ_XCOMP_PERM)`,
/// asked once).
pub fn amx_available() -> bool {
    static BF16: std::sync::OnceLock<bool> = std::sync::OnceLock::new();
    *BF16.get_or_init(|| tiles_available(AMX_BF16))
}

/// The same for AMX-INT8 (`TDPBUSD`).
pub fn amx_int8_available() -> bool {
    static INT8: std::sync::OnceLock<bool> = std::sync::OnceLock::new();
    *INT8.get_or_init(|| tiles_available(AMX_INT8))
}

/// CPUID.(7,0):EDX bits of AMX-BF16 and AMX-INT8.
const AMX_BF16: u32 = 1 << 22;
const AMX_INT8: u32 = 1 << 25;

/// Whether the core has AMX-TILE and the instructions of `edx_bit`, and the tile state is
/// granted (asked once per process). Its callers keep the answer, as the standard library keeps
/// `is_x86_feature_detected!`'s.
fn tiles_available(edx_bit: u32) -> bool {
    #[cfg(target_arch = "x86_64")]
    {
        static GRANTED: std::sync::OnceLock<bool> = std::sync::OnceLock::new();
        amx_in_cpu(edx_bit) && *GRANTED.get_or_init(amx_granted)
    }
    #[cfg(not(target_arch = "x86_64"))]
    {
        let _ = edx_bit;
        false
    }
}

/// CPUID.(7,0):EDX `edx_bit` and bit 24 (AMX-TILE); XCR0 bits 17 and 18 (tile config and data)
/// enabled by the OS.
#[cfg(target_arch = "x86_64")]
fn amx_in_cpu(edx_bit: u32) -> bool {
    use std::arch::x86_64::{__cpuid, __cpuid_count, _xgetbv};
    // SAFETY: CPUID is on every x86-64 core; XGETBV only where CPUID says OSXSAVE.
    unsafe {
        if __cpuid(0).eax < 7 {
            return false;
        }
        let edx = __cpuid_count(7, 0).edx;
        let osxsave = __cpuid(1).ecx & (1 << 27) != 0;
        let tiles = edx & edx_bit != 0 && edx & (1 << 24) != 0;
        tiles && osxsave && (_xgetbv(0) >> 17) & 0b11 == 0b11
    }
}

/// Linux hands the tile data state out on request; other systems are assumed to enable it
/// wherever XCR0 does.
#[cfg(target_arch = "x86_64")]
fn amx_granted() -> bool {
    #[cfg(target_os = "linux")]
    {
        const ARCH_REQ_XCOMP_PERM: libc::c_long = 0x1023;
        const XFEATURE_XTILEDATA: libc::c_long = 18;
        // SAFETY: arch_prctl with these arguments only changes this process's permission.
        let granted = unsafe {
            libc::syscall(
                libc::SYS_arch_prctl,
                ARCH_REQ_XCOMP_PERM,
                XFEATURE_XTILEDATA,
            )
        } == 0;
        if !granted {
            tracing::warn!("the core has AMX but the OS refused its tile state; not using AMX");
        }
        granted
    }
    #[cfg(not(target_os = "linux"))]
    {
        true
    }
}

/// Whether the native kernel runs here: AMX granted, and AVX-512 BF16 for its epilogue.
fn native_available() -> bool {
    amx_available() && super::bf16::native_available()
}

/// bfloat16 pairs on AMX tiles.
#[derive(Debug, Clone, Copy)]
pub struct AmxBf16;

kernel_impl!(AmxBf16, u16, group 2, inputs K_STEP, mr MR, nr NR,
    available native_available, convert to_bf16, gemm gemm_amx);

/// [`Kernel::gemm`] on the core's tiles.
///
/// # Safety
/// As [`Kernel::gemm`], and [`native_available`] holds.
#[cfg(target_arch = "x86_64")]
unsafe fn gemm_amx(
    layer: &Packed<u16>,
    bias: &[f32],
    input: &[u16],
    stride: usize,
    rows: usize,
    epilogue: Epilogue<'_, u16>,
) {
    // SAFETY: the caller's contract; `finish_avx512` needs what `native_available` checked.
    unsafe {
        gemm_tiles(
            (&mut AmxTiles, finish_avx512),
            layer,
            bias,
            input,
            stride,
            rows,
            epilogue,
        )
    }
}

/// The same kernel on [`EmulatedTiles`] (its epilogue on AVX-512 where the core has it): on any
/// core, for the tests.
#[derive(Debug, Clone, Copy)]
pub(super) struct EmulatedAmxBf16;

kernel_impl!(EmulatedAmxBf16, u16, group 2, inputs K_STEP, mr MR, nr NR,
    available always, convert to_bf16, gemm gemm_emulated);

fn always() -> bool {
    true
}

/// [`Kernel::gemm`] on [`EmulatedTiles`].
///
/// # Safety
/// As [`Kernel::gemm`].
#[cfg(target_arch = "x86_64")]
unsafe fn gemm_emulated(
    layer: &Packed<u16>,
    bias: &[f32],
    input: &[u16],
    stride: usize,
    rows: usize,
    epilogue: Epilogue<'_, u16>,
) {
    let finish: Finish = if super::bf16::native_available() {
        finish_avx512
    } else {
        finish_scalar
    };
    // SAFETY: the caller's contract; `finish_avx512` only where the core has it.
    unsafe {
        gemm_tiles(
            (&mut EmulatedTiles::new(), finish),
            layer,
            bias,
            input,
            stride,
            rows,
            epilogue,
        )
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// `TDPBF16PS` on the emulated tiles as the manual defines it: row `m` of A times the pairs
    /// of B's row `k`, added into C's row `m`, column `n`, from tiles loaded with strides.
    #[test]
    fn the_emulated_tile_product_follows_the_manual() {
        // A: 16 rows of 32 bf16, a[m][i] = m + i/8; B: 16 rows of 16 pairs, b[k][2n + t] =
        // (n − k + t) / 4; both in buffers wider than a tile row (strides of 80 and 96 bytes).
        let value = |x: f32| to_bf16(x).to_le_bytes();
        let mut a = vec![0u8; 16 * 80];
        let mut b = vec![0u8; 16 * 96];
        for m in 0..16 {
            for i in 0..32 {
                a[m * 80 + 2 * i..][..2].copy_from_slice(&value(m as f32 + i as f32 / 8.0));
            }
        }
        for k in 0..16 {
            for n in 0..16 {
                for t in 0..2 {
                    let v = (n as f32 - k as f32 + t as f32) / 4.0;
                    b[k * 96 + 4 * n + 2 * t..][..2].copy_from_slice(&value(v));
                }
            }
        }
        let mut c = vec![0f32; 16 * 16];
        let mut tiles = EmulatedTiles::new();
        // SAFETY: every row read or written lies in the buffers above.
        unsafe {
            tiles.configure();
            tiles.zero::<0>();
            tiles.load::<4>(a.as_ptr(), 80);
            tiles.load::<6>(b.as_ptr(), 96);
            tiles.dot::<0, 4, 6>();
            tiles.dot::<0, 4, 6>();
            tiles.store::<0>(c.as_mut_ptr() as *mut u8, 64);
            tiles.release();
        }
        for m in 0..16 {
            for n in 0..16 {
                let want: f64 = (0..16)
                    .flat_map(|k| (0..2).map(move |t| (k, t)))
                    .map(|(k, t)| {
                        let a = m as f64 + (2 * k + t) as f64 / 8.0;
                        let b = (n as f64 - k as f64 + t as f64) / 4.0;
                        2.0 * a * b
                    })
                    .sum();
                let got = c[m * 16 + n] as f64;
                assert!(
                    (got - want).abs() <= 1e-4 * want.abs().max(1.0),
                    "C[{m}][{n}] {got} {want}"
                );
            }
        }
    }

    /// `TDPBUSD` on the emulated tiles: A's bytes unsigned, B's signed, four products per i32
    /// sum, added into C (which starts at −1 000 here).
    #[test]
    fn the_emulated_byte_product_takes_a_unsigned_and_b_signed() {
        // a[m][i] = (37m + 11i) mod 256, b[k][4n + t] = (13k + 7n + 5t) mod 256 as signed.
        let a: Vec<u8> = (0..16 * 64)
            .map(|j| ((37 * (j / 64) + 11 * (j % 64)) % 256) as u8)
            .collect();
        let b: Vec<u8> = (0..16 * 64)
            .map(|j| ((13 * (j / 64) + 7 * (j % 64 / 4) + 5 * (j % 4)) % 256) as u8)
            .collect();
        let mut c = vec![-1000i32; 16 * 16];
        let mut tiles = EmulatedTiles::new();
        // SAFETY: every row read or written lies in the buffers above.
        unsafe {
            tiles.configure();
            tiles.load::<0>(c.as_ptr() as *const u8, 64);
            tiles.load::<4>(a.as_ptr(), 64);
            tiles.load::<6>(b.as_ptr(), 64);
            tiles.dot_bytes::<0, 4, 6>();
            tiles.store::<0>(c.as_mut_ptr() as *mut u8, 64);
            tiles.release();
        }
        for m in 0..16 {
            for n in 0..16 {
                let want: i64 = -1000
                    + (0..16)
                        .flat_map(|k| (0..4).map(move |t| (k, t)))
                        .map(|(k, t)| {
                            a[m * 64 + 4 * k + t] as i64 * b[k * 64 + 4 * n + t] as i8 as i64
                        })
                        .sum::<i64>();
                assert_eq!(c[m * 16 + n] as i64, want, "C[{m}][{n}]");
            }
        }
        assert!(b.iter().any(|&v| (v as i8) < 0) && a.iter().any(|&v| v > 127));
    }

    /// The tile configuration is palette 1 with 8 tiles of 16 rows × 64 bytes, and nothing else.
    #[test]
    fn the_tile_configuration_is_palette_1_with_full_tiles() {
        let c = TileConfig::all_full().0;
        assert_eq!(c[0], 1);
        assert!(c[1..16].iter().all(|&b| b == 0));
        for t in 0..8 {
            assert_eq!(u16::from_le_bytes([c[16 + 2 * t], c[17 + 2 * t]]), 64);
            assert_eq!(c[48 + t], 16);
        }
        assert!(c[32..48].iter().all(|&b| b == 0));
        assert!(c[56..].iter().all(|&b| b == 0));
    }

    /// The peak probes' loop: each round adds 32 · 2⁻¹⁰ to every sum of every accumulator (64 in
    /// bytes).
    #[test]
    fn the_peak_probes_rounds_add_up() {
        // SAFETY: emulated tiles.
        let sum = unsafe { tile_rounds::<_, false>(&mut EmulatedTiles::new(), 3) };
        assert_eq!(sum, 3.0 * 32.0 / 1024.0);
        // SAFETY: emulated tiles.
        let sum = unsafe { tile_rounds::<_, true>(&mut EmulatedTiles::new(), 3) };
        assert_eq!(sum, 3.0 * 64.0);
    }

    /// The two epilogues give the same activations (bfloat16 bits) and output dot products; the
    /// scalar one is what the emulation runs on cores without AVX-512 BF16.
    #[test]
    fn the_vector_and_scalar_epilogues_agree() {
        if !super::super::bf16::native_available() {
            return;
        }
        let block: Block = std::array::from_fn(|i| ((i * 37 % 101) as f32 - 50.0) / 7.0);
        let bias: Vec<f32> = (0..2 * NR).map(|i| (i % 9) as f32 / 4.0 - 1.0).collect();
        let weights: Vec<f32> = (0..2 * NR).map(|i| (i % 5) as f32 / 3.0 - 0.5).collect();
        let (rows, stride) = (2 * MR, 2 * NR);
        let run = |finish: Finish| {
            let mut out = vec![0u16; rows * stride];
            let mut dots = vec![0.5f32; rows];
            for (panel, r0) in [(0, 0), (1, MR)] {
                let mut store = Epilogue::Store {
                    out: &mut out,
                    stride,
                };
                let mut dot = Epilogue::Dot {
                    weights: &weights,
                    dots: &mut dots,
                };
                // SAFETY: the buffers hold both blocks' rows and both panels' columns; the core
                // has AVX-512 BF16 (checked above).
                unsafe {
                    finish(&block, &bias, panel, r0, &mut store);
                    finish(&block, &bias, panel, r0, &mut dot);
                }
            }
            (out, dots)
        };
        let (vector, scalar) = (run(finish_avx512), run(finish_scalar));
        assert_eq!(vector.0, scalar.0);
        for (v, s) in vector.1.iter().zip(&scalar.1) {
            assert!((v - s).abs() <= 1e-4 * s.abs().max(1.0), "{v} {s}");
        }
        assert!(vector.0.iter().any(|&h| h != 0) && vector.0.contains(&0));
    }

    /// An instruction on tiles never configured is refused, as the core would fault.
    #[test]
    #[should_panic(expected = "before LDTILECFG")]
    fn the_emulated_tiles_refuse_work_before_configuration() {
        let mut tiles = EmulatedTiles::new();
        // SAFETY: the emulation checks the configuration before touching memory.
        unsafe { tiles.zero::<0>() };
    }
}
