//! The head's own GEMM kernels and the tile driver they share. A kernel multiplies row blocks of
//! a tile's activations by weights packed once into column panels, and applies bias and ReLU as
//! each block leaves the registers (or, after a branch's last hidden layer, the `width → 1` dot
//! product), so no intermediate leaves the tile. Five kernels use the driver:
//!
//! - [`F32Avx512`]: f32 on 512-bit FMAs (AVX-512F), blocks of 12 rows × 32 columns: the 32 KiB
//!   panel of a 256-wide layer and the block's 12 rows stay in L1 (measured fastest of 4×64,
//!   6×64, 12×32, 14×32, 8×48 with `examples/probe_kernels.rs`). Each row's inputs are
//!   broadcast from the row itself: copying a block's rows into one stream first (as GEMM
//!   libraries pack) made the head 18 % slower on the Intel Xeon (72 % of the FMA peak against
//!   88 %, level 4). The padded widths 128, 256 and 512 run with the row stride a constant,
//!   so a row's broadcast is one load at a fixed displacement: with the stride in a register,
//!   about 10 of the loop's 50 instructions were address arithmetic, taking FMA ports' slots.
//!   Tiles are whole register blocks ([`super::tiles::blocked_tile_rows`]: 264 rows, not 256
//!   rows computed as 264). With both, the four-input trip and no `memset` of the first layer,
//!   the f32 head read 72–75 % of the FMA peak on the Intel Xeon at level 3 against 65–71 %
//!   before, in one window with `examples/probe_full_grid.rs` (BENCHMARKS, "The f32 kernels
//!   with the row stride a constant").
//! - [`F32Avx2`]: f32 on 256-bit FMAs (AVX2 + FMA), blocks of 6 rows × 16 columns.
//! - [`Bf16Kernel`](super::bf16): `VDPBF16PS` on AVX-512 BF16 cores.
//! - [`F16Kernel`](super::f16): `VFMADD231PH` on AVX-512 FP16 cores.
//! - [`AmxBf16`](super::amx): `TDPBF16PS` on AMX tiles, blocks of 32 rows × 32 columns.
//!
//! The portable path is the library GEMM of `net::dense`, for cores with neither (or
//! when asked for).
//!
//! Weights are packed as `[panel][group][NR][GROUP]`: `GROUP` consecutive inputs per 32-bit lane
//! (2 for bfloat16 pairs, 1 for f32 and f16), `NR` columns per panel.

use std::marker::PhantomData;

use super::dense::Dense;
use super::tiles::{Branches, Rows, blocked_tile_rows, by_tiles};
use super::weights::HeadWeights;

/// A GEMM kernel of the driver: its element type and its block shape.
pub(super) trait Kernel: Send + Sync {
    /// What packed weights and activations hold.
    type Elem: Copy + Default + Send + Sync + std::fmt::Debug;
    /// Consecutive inputs per 32-bit lane.
    const GROUP: usize;
    /// Rows of the register block.
    const MR: usize;
    /// Columns of the register block and of a packed panel (even).
    const NR: usize;
    /// A layer's inputs are padded to a multiple of this (a multiple of [`Kernel::GROUP`]; the
    /// AMX kernel reads 32 at a time).
    const INPUTS: usize = Self::GROUP;
    /// Whether this core has the kernel's instructions.
    fn available() -> bool;
    /// An f32 as the kernel's element.
    fn convert(x: f32) -> Self::Elem;
    /// [`Kernel::convert`] of each of `src` into `dst` (a kernel may override it with vector
    /// instructions).
    fn convert_row(src: &[f32], dst: &mut [Self::Elem]) {
        for (d, &s) in dst.iter_mut().zip(src) {
            *d = Self::convert(s);
        }
    }
    /// `relu(input · W + bias)` for `rows` (a multiple of [`Kernel::MR`]) rows of `input` (rows
    /// of `stride`), through `epilogue`.
    ///
    /// # Safety
    /// [`Kernel::available`] holds; `layer` was packed with [`Kernel::NR`]; `bias` holds
    /// `layer.panels × NR` values; `input` holds `rows × stride` values with `stride ≥ GROUP ×
    /// layer.groups`; a `Store` output holds `rows` rows of its stride, which is at least
    /// `layer.panels × NR`; a `Dot`'s `dots` hold `rows` values and its weights
    /// `layer.panels × NR`.
    unsafe fn gemm(
        layer: &Packed<Self::Elem>,
        bias: &[f32],
        input: &[Self::Elem],
        stride: usize,
        rows: usize,
        epilogue: Epilogue<'_, Self::Elem>,
    );
}

/// One layer's weights as column panels.
#[derive(Debug, Clone)]
pub(super) struct Packed<E> {
    /// Input groups (inputs rounded up to a multiple of the group).
    pub(super) groups: usize,
    /// Column panels of `NR` (outputs rounded up).
    pub(super) panels: usize,
    /// `[panel][group][NR][GROUP]`, zero past the inputs and outputs.
    pub(super) weight: Vec<E>,
    /// `[panels × NR]`, zero past the outputs.
    pub(super) bias: Vec<f32>,
}

impl<E: Copy + Default> Packed<E> {
    /// `dense` in panels of `nr` columns, taking `padded_inputs` inputs (≥ its own, a multiple
    /// of `group`; the extra ones weigh zero), each weight converted by `convert`.
    pub(super) fn of(
        dense: &Dense,
        padded_inputs: usize,
        (group, nr): (usize, usize),
        convert: fn(f32) -> E,
    ) -> Packed<E> {
        let groups = padded_inputs / group;
        let panels = dense.outputs.div_ceil(nr);
        let mut weight = vec![E::default(); panels * groups * nr * group];
        for panel in 0..panels {
            for g in 0..groups {
                for c in 0..nr {
                    for t in 0..group {
                        let (i, o) = (group * g + t, panel * nr + c);
                        if i < dense.inputs && o < dense.outputs {
                            weight[((panel * groups + g) * nr + c) * group + t] =
                                convert(dense.weight[i * dense.outputs + o]);
                        }
                    }
                }
            }
        }
        let mut bias = dense.bias.clone();
        bias.resize(panels * nr, 0.0);
        Packed {
            groups,
            panels,
            weight,
            bias,
        }
    }
}

/// What leaves a GEMM's register block.
pub(super) enum Epilogue<'a, E> {
    /// `relu(acc + b)` as rows of `stride`.
    Store { out: &'a mut [E], stride: usize },
    /// `Σ_j relu(acc + b)_j · w_j` added to `dots[row]`.
    Dot {
        weights: &'a [f32],
        dots: &'a mut [f32],
    },
}

/// One branch, packed.
#[derive(Debug, Clone)]
struct NativeBranch<E> {
    hidden: Vec<Packed<E>>,
    /// The output weights, zero-padded to the padded width.
    output: Vec<f32>,
    output_bias: f32,
}

/// The head on one of the project's kernels.
#[derive(Debug, Clone)]
pub(super) struct NativeHead<K: Kernel> {
    width: usize,
    /// Width rounded up to the kernel's [`Kernel::NR`]: the stride of every activation row.
    padded: usize,
    /// The rotation half of the first layer (its bias included).
    rotation: Packed<K::Elem>,
    /// Length of a rotation's encoding.
    encoding: usize,
    branches: [NativeBranch<K::Elem>; 2],
    kernel: PhantomData<K>,
}

/// One task's buffers: encodings, the shared input, two activation buffers, and the output dot
/// products.
struct Scratch<E> {
    /// One row of the shared input in f32, before conversion.
    row: Vec<f32>,
    e: Vec<E>,
    x: Vec<E>,
    a: Vec<E>,
    b: Vec<E>,
    dots: Vec<f32>,
}

impl<K: Kernel> NativeHead<K> {
    /// Packs `head`'s weights (as they are: a bfloat16 head reads them rounded), or `None` when
    /// this core lacks the kernel's instructions or a branch has no hidden layer.
    pub(super) fn new(head: &HeadWeights) -> Option<NativeHead<K>> {
        if !K::available() {
            return None;
        }
        let width = head.width;
        let padded = width.next_multiple_of(K::NR).next_multiple_of(K::INPUTS);
        debug_assert!(
            padded.is_multiple_of(K::NR),
            "NR and INPUTS are powers of two"
        );
        let branches = head
            .square_branches(padded)?
            .map(|(hidden, output, output_bias)| NativeBranch {
                hidden: hidden
                    .iter()
                    .map(|d| Packed::of(d, padded, (K::GROUP, K::NR), K::convert))
                    .collect(),
                output,
                output_bias,
            });
        let rotation = &head.rotation;
        let rotation_inputs = rotation.inputs.next_multiple_of(K::INPUTS);
        Some(NativeHead {
            width,
            padded,
            rotation: Packed::of(rotation, rotation_inputs, (K::GROUP, K::NR), K::convert),
            encoding: rotation.inputs,
            branches,
            kernel: PhantomData,
        })
    }

    /// The `branches`' log-weights of `rows` (0 for a branch left out). From encodings, the
    /// rotation half of the first layer runs inside the tiles too (no projection pass).
    pub(super) fn branch_scores(
        &self,
        image_term: &[f32],
        rows: Rows<'_>,
        branches: Branches,
    ) -> (Vec<f32>, Vec<f32>) {
        let (given, per_row) = match rows {
            Rows::Projected(p) => (p, self.width),
            Rows::Encoded(e) => (e, self.encoding),
        };
        // The first layer's bias with the image's term in it, for encoded rows.
        let mut first_bias = self.rotation.bias.clone();
        for (b, i) in first_bias.iter_mut().zip(image_term) {
            *b += i;
        }
        let blocked = blocked_tile_rows(K::MR);
        by_tiles(
            given,
            per_row,
            blocked,
            branches,
            || Scratch {
                row: vec![0.0; self.width],
                e: vec![K::Elem::default(); blocked * K::GROUP * self.rotation.groups],
                x: vec![K::Elem::default(); blocked * self.padded],
                a: vec![K::Elem::default(); blocked * self.padded],
                b: vec![K::Elem::default(); blocked * self.padded],
                dots: vec![0.0; blocked],
            },
            |scratch, given, out| {
                let tile = match rows {
                    Rows::Projected(_) => Rows::Projected(given),
                    Rows::Encoded(_) => Rows::Encoded(given),
                };
                self.tile(image_term, &first_bias, tile, scratch, out);
            },
        )
    }

    /// One tile of rows: the shared input `relu(P_R + W_I·f + b)`, then each branch `out` holds
    /// an output for (the shape branch first).
    fn tile(
        &self,
        image_term: &[f32],
        first_bias: &[f32],
        given: Rows<'_>,
        scratch: &mut Scratch<K::Elem>,
        out: &mut [&mut [f32]],
    ) {
        let stride = self.padded;
        let rows = out[0].len();
        let blocked = rows.div_ceil(K::MR) * K::MR;
        let Scratch {
            row,
            e,
            x,
            a,
            b,
            dots,
        } = scratch;
        match given {
            Rows::Projected(projected) => {
                // Every value of the `blocked` rows is written: the rows' own, then zeros past
                // the width and in the padding rows (no pass that clears them all first).
                let w = self.width;
                for (xr, pr) in x.chunks_exact_mut(stride).zip(projected.chunks_exact(w)) {
                    for ((r, &p), &i) in row.iter_mut().zip(pr).zip(image_term) {
                        *r = (p + i).max(0.0);
                    }
                    K::convert_row(row, &mut xr[..w]);
                    xr[w..].fill(K::Elem::default());
                }
                x[rows * stride..blocked * stride].fill(K::Elem::default());
            }
            Rows::Encoded(encodings) => {
                let e_stride = K::GROUP * self.rotation.groups;
                e[..blocked * e_stride].fill(K::Elem::default());
                for (er, enc) in e
                    .chunks_exact_mut(e_stride)
                    .zip(encodings.chunks_exact(self.encoding))
                {
                    K::convert_row(enc, er);
                }
                let epilogue = Epilogue::Store { out: x, stride };
                // SAFETY: `K::available()` held when this head was built and its layers were
                // packed with `K::NR`; `e` holds `blocked` rows of `e_stride` = GROUP × groups,
                // `x` `blocked` rows of `stride` ≥ the layer's panels × NR, and `first_bias` as
                // many values.
                unsafe { K::gemm(&self.rotation, first_bias, e, e_stride, blocked, epilogue) };
            }
        }
        for (branch, out) in self.branches.iter().zip(out.iter_mut()) {
            let last = branch.hidden.len() - 1;
            let dots = &mut dots[..blocked];
            dots.fill(branch.output_bias);
            for (l, layer) in branch.hidden.iter().enumerate() {
                // Layer l reads x (l = 0), a (odd l) or b, and writes the other of a and b.
                let (input, output) = match l {
                    0 => (&x[..], &mut a[..]),
                    l if l % 2 == 1 => (&a[..], &mut b[..]),
                    _ => (&b[..], &mut a[..]),
                };
                let epilogue = if l == last {
                    Epilogue::Dot {
                        weights: &branch.output,
                        dots: &mut *dots,
                    }
                } else {
                    Epilogue::Store {
                        out: output,
                        stride,
                    }
                };
                // SAFETY: as above; `input` holds `blocked` rows of `stride` = GROUP × the
                // layer's groups, and the epilogue's buffers hold `blocked` rows.
                unsafe { K::gemm(layer, &layer.bias, input, stride, blocked, epilogue) };
            }
            out.copy_from_slice(&dots[..rows]);
        }
    }
}

/// Whether this core has AVX-512F (the f32 kernel's 512-bit FMAs).
pub fn avx512f_available() -> bool {
    #[cfg(target_arch = "x86_64")]
    {
        std::is_x86_feature_detected!("avx512f")
    }
    #[cfg(not(target_arch = "x86_64"))]
    {
        false
    }
}

/// The [`Kernel`] impl of a kernel whose `gemm` is the x86-64 function `$gemm` (taking the
/// trait's arguments); elsewhere `available` is false and `gemm` is never called.
macro_rules! kernel_impl {
    ($kernel:ty, $elem:ty, group $group:expr, $(inputs $inputs:expr,)? mr $mr:expr, nr $nr:expr,
     available $available:path, convert $convert:path, gemm $gemm:path
     $(, convert_row $convert_row:path)?) => {
        impl Kernel for $kernel {
            type Elem = $elem;
            const GROUP: usize = $group;
            const MR: usize = $mr;
            const NR: usize = $nr;
            $(const INPUTS: usize = $inputs;)?

            fn available() -> bool {
                $available()
            }

            fn convert(x: f32) -> $elem {
                $convert(x)
            }

            $(
                fn convert_row(src: &[f32], dst: &mut [$elem]) {
                    $convert_row(src, dst)
                }
            )?

            unsafe fn gemm(
                layer: &Packed<$elem>,
                bias: &[f32],
                input: &[$elem],
                stride: usize,
                rows: usize,
                epilogue: Epilogue<'_, $elem>,
            ) {
                #[cfg(target_arch = "x86_64")]
                // SAFETY: the caller's contract is the kernel function's.
                unsafe {
                    $gemm(layer, bias, input, stride, rows, epilogue)
                }
                #[cfg(not(target_arch = "x86_64"))]
                {
                    let _ = (layer, bias, input, stride, rows, epilogue);
                    unreachable!("the native kernels are only built on x86_64")
                }
            }
        }
    };
}
pub(super) use kernel_impl;

/// `$instance::<STRIDE>(args…)` with the row stride a constant where it is one of the padded
/// widths 128, 256 and 512 (`STRIDE` 0: read at run time otherwise), so that a kernel's
/// broadcasts are loads at fixed displacements: the dispatch of the f32 kernels here and of the
/// 8-bit ones (`net::i8`).
macro_rules! with_constant_stride {
    ($stride:expr, $instance:ident($($arg:expr),* $(,)?)) => {
        match $stride {
            256 => $instance::<256>($($arg),*),
            128 => $instance::<128>($($arg),*),
            512 => $instance::<512>($($arg),*),
            _ => $instance::<0>($($arg),*),
        }
    };
}
pub(super) use with_constant_stride;

/// An f32 [`Kernel::gemm`] on one vector width: blocks of `MR` rows × `NV` vectors of `LANES`
/// lanes, each row's input broadcast from its own row, bias and ReLU (or the output dot
/// product) as each block leaves the registers. `$hsum` sums a vector's lanes.
macro_rules! f32_gemm {
    ($(#[$doc:meta])* $name:ident, $feature:literal, $v:ty, lanes $lanes:literal, mr $mr:literal,
     nv $nv:literal, $zero:ident, $load:ident, $store:ident, $set1:ident, $fmadd:ident,
     $add:ident, $max:ident, $hsum:path) => {
        $(#[$doc])*
        ///
        /// The common input strides (the padded widths 128, 256 and 512) run an instance with
        /// the stride a constant, so each row's broadcast is one load at a fixed displacement
        /// from the block: no address arithmetic in the loop to take the FMA ports' slots.
        ///
        /// # Safety
        /// As [`Kernel::gemm`], with the target features named.
        #[cfg(target_arch = "x86_64")]
        #[target_feature(enable = $feature)]
        unsafe fn $name(
            layer: &Packed<f32>,
            bias: &[f32],
            input: &[f32],
            stride: usize,
            rows: usize,
            epilogue: Epilogue<'_, f32>,
        ) {
            #[target_feature(enable = $feature)]
            unsafe fn by_stride<const STRIDE: usize>(
                layer: &Packed<f32>,
                bias: &[f32],
                input: &[f32],
                stride: usize,
                rows: usize,
                epilogue: Epilogue<'_, f32>,
            ) {
                use std::arch::x86_64::*;
                const MR: usize = $mr;
                const NV: usize = $nv;
                let stride = if STRIDE == 0 { stride } else { STRIDE };
                let nr = $lanes * NV;
                debug_assert!(
                    rows.is_multiple_of(MR)
                        && input.len() >= rows * stride
                        && stride >= layer.groups
                        && bias.len() >= layer.panels * nr
                );
                let k = layer.groups;
                let mut epilogue = epilogue;
                for panel in 0..layer.panels {
                    for r0 in (0..rows).step_by(MR) {
                        // SAFETY (all pointer reads and writes below): within the bounds above.
                        unsafe {
                            let weights = layer.weight.as_ptr().add(panel * k * nr);
                            let bias: [$v; NV] = std::array::from_fn(|c| {
                                $load(bias.as_ptr().add(panel * nr + $lanes * c))
                            });
                            let mut acc = [[$zero(); NV]; MR];
                            let block = input.as_ptr().add(r0 * stride);
                            // Four inputs a trip (the loop's own instructions would take FMA
                            // ports' slots), then the rest one by one.
                            let unrolled = k - k % 4;
                            let mut i = 0;
                            while i < k {
                                let trip = if i < unrolled { 4 } else { 1 };
                                for u in 0..trip {
                                    let w = weights.add((i + u) * nr);
                                    let a = block.add(i + u);
                                    let b: [$v; NV] =
                                        std::array::from_fn(|c| $load(w.add($lanes * c)));
                                    for (r, acc) in acc.iter_mut().enumerate() {
                                        let x = $set1(*a.add(r * stride));
                                        for c in 0..NV {
                                            acc[c] = $fmadd(x, b[c], acc[c]);
                                        }
                                    }
                                }
                                i += trip;
                            }
                            let zero = $zero();
                            for (r, acc) in acc.iter().enumerate() {
                                let row = r0 + r;
                                let h: [$v; NV] =
                                    std::array::from_fn(|c| $max($add(acc[c], bias[c]), zero));
                                match &mut epilogue {
                                    Epilogue::Store { out, stride } => {
                                        let o = out.as_mut_ptr().add(row * *stride + panel * nr);
                                        for (c, h) in h.iter().enumerate() {
                                            $store(o.add($lanes * c), *h);
                                        }
                                    }
                                    Epilogue::Dot { weights, dots } => {
                                        let w = weights.as_ptr().add(panel * nr);
                                        let mut sum = $zero();
                                        for (c, h) in h.iter().enumerate() {
                                            sum = $fmadd(*h, $load(w.add($lanes * c)), sum);
                                        }
                                        dots[row] += $hsum(sum);
                                    }
                                }
                            }
                        }
                    }
                }
            }
            // SAFETY: the caller's contract; each instance reads `stride` as given.
            unsafe {
                with_constant_stride!(
                    stride,
                    by_stride(layer, bias, input, stride, rows, epilogue)
                )
            }
        }
    };
}

/// Whether this core has AVX2 and FMA (the 256-bit f32 kernel).
pub fn avx2_available() -> bool {
    #[cfg(target_arch = "x86_64")]
    {
        std::is_x86_feature_detected!("avx2") && std::is_x86_feature_detected!("fma")
    }
    #[cfg(not(target_arch = "x86_64"))]
    {
        false
    }
}

/// f32 on 512-bit FMAs: blocks of 12 rows × 2 sixteen-lane vectors.
#[derive(Debug, Clone, Copy)]
pub struct F32Avx512;

kernel_impl!(F32Avx512, f32, group 1, mr 12, nr 32, available avx512f_available,
    convert std::convert::identity, gemm gemm_f32_avx512);

f32_gemm!(
    /// [`Kernel::gemm`] for f32 on AVX-512F, blocks of 12 rows × 32 columns.
    gemm_f32_avx512, "avx512f", __m512, lanes 16, mr 12, nv 2, _mm512_setzero_ps,
    _mm512_loadu_ps, _mm512_storeu_ps, _mm512_set1_ps, _mm512_fmadd_ps, _mm512_add_ps,
    _mm512_max_ps, _mm512_reduce_add_ps
);

/// f32 on 256-bit FMAs: blocks of 6 rows × 2 eight-lane vectors (12 accumulators, 2 weight
/// vectors and a broadcast in the 16 ymm registers).
#[derive(Debug, Clone, Copy)]
pub struct F32Avx2;

kernel_impl!(F32Avx2, f32, group 1, mr 6, nr 16, available avx2_available,
    convert std::convert::identity, gemm gemm_f32_avx2);

f32_gemm!(
    /// [`Kernel::gemm`] for f32 on AVX2, blocks of 6 rows × 16 columns.
    gemm_f32_avx2, "avx2,fma", __m256, lanes 8, mr 6, nv 2, _mm256_setzero_ps,
    _mm256_loadu_ps, _mm256_storeu_ps, _mm256_set1_ps, _mm256_fmadd_ps, _mm256_add_ps,
    _mm256_max_ps, hsum256
);

/// The sum of a 256-bit vector's lanes.
///
/// # Safety
/// The core has AVX.
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx")]
pub(super) unsafe fn hsum256(v: std::arch::x86_64::__m256) -> f32 {
    use std::arch::x86_64::*;
    let mut lanes = [0f32; 8];
    // SAFETY: `lanes` holds 8 floats.
    unsafe { _mm256_storeu_ps(lanes.as_mut_ptr(), v) };
    lanes.iter().sum()
}

/// `Σ_j h_j · w_j` over a block row's `N` vectors (the `width → 1` output layer).
///
/// # Safety
/// The core has AVX-512F; `w` points at `16 N` floats.
#[cfg(target_arch = "x86_64")]
#[inline]
#[target_feature(enable = "avx512f")]
pub(super) unsafe fn dot<const N: usize>(h: &[std::arch::x86_64::__m512; N], w: *const f32) -> f32 {
    use std::arch::x86_64::*;
    // SAFETY: `w` holds 16 N floats.
    unsafe {
        let mut sum = _mm512_mul_ps(h[0], _mm512_loadu_ps(w));
        for (c, h) in h.iter().enumerate().skip(1) {
            sum = _mm512_fmadd_ps(*h, _mm512_loadu_ps(w.add(16 * c)), sum);
        }
        _mm512_reduce_add_ps(sum)
    }
}
