//! The fused head in 8-bit integers, for the coarse levels of a search on cores with AVX-512
//! VNNI. `VPDPBUSD` multiplies 64 unsigned by 64 signed bytes and adds them four by four into
//! 16 i32 lanes: at the f32 FMA's instruction rate, four times its arithmetic (twice f16's).
//! Its 256-bit AVX-VNNI form runs the same head where the kernels are capped at 256 bits or the
//! core has no AVX-512 (Intel cores since Alder Lake). A core with AVX2 and no VNNI at all (AMD
//! before Zen 4, Intel before Ice Lake) runs it on `VPMADDWD`: bytes widened to 16-bit pairs,
//! two products summed into each i32 lane, the same exact sums at about twice the f32 FMA's
//! arithmetic on such cores.
//!
//! What is rounded, and how ([`super::tiles`]):
//! - each layer's weights to signed bytes with one scale per output column
//!   ([`columns_to_i8`]: the column's largest |w| is 127);
//! - each row of activations (ReLU outputs, never negative) to unsigned bytes with the row's own
//!   scale ([`row_to_u8`]: the row's maximum is 255), so a row of small values keeps its
//!   resolution;
//! - encodings (sines and cosines) to a fixed grid of [−1, 1] ([`encoding_to_u8`]:
//!   `u = (e + 1)·127.5`); the offset is folded into the first layer's bias.
//!
//! The integer sums are exact; each block leaves the registers as `relu(acc · s_row · s_col + b)`
//! in f32, and a layer's rows are rounded to bytes again once all their columns are out (a row's
//! scale needs its maximum). The branches' last hidden layer feeds the f32 output dot product.
//! Elsewhere the same rounding is emulated on the f32 GEMM (`FusedHead`'s emulation), so a
//! search ranks the same cells on any machine, up to the order of the f32 sums.
//!
//! Where the core has AMX-INT8 (and the kernels are not capped), the same GEMMs run on tiles
//! (`TDPBUSD`, [`super::amx::gemm_i8_tiles`], blocks of 32 rows × 32 columns) reading the same
//! packed bytes; the integer sums are the same, so are the scores up to the order of the
//! output dot product's f32 sums.

use super::amx::{self, BytesScales};
use super::dense::Dense;
use super::kernels::Kernels;
use super::native::{Epilogue, Packed, avx2_available, with_constant_stride};
use super::tiles::{
    Branches, ENCODING_SCALE, Rows, blocked_tile_rows, by_tiles, columns_to_i8, encoding_to_u8,
    row_to_u8,
};
use super::weights::HeadWeights;

/// Rows of the kernel's register block.
pub const MR: usize = 6;
/// Columns of the kernel's register block (four 16-lane vectors).
pub const NR: usize = 64;
/// Inputs per 32-bit lane of `VPDPBUSD`.
const GROUP: usize = 4;
/// Inputs per 32-bit lane of `VPMADDWD` (two 16-bit products).
const PAIR: usize = 2;
/// The name of the `VPMADDWD` kernel ([`I8Head::kernel_name`]).
pub const KERNEL_NAME_PAIRS: &str = "AVX2 kernel on 16-bit pairs (VPMADDWD)";

/// The instructions an [`I8Head`] runs on.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum Isa {
    /// AVX-512 VNNI: 512-bit `VPDPBUSD`, blocks of 6 rows × 64 columns.
    Avx512,
    /// AVX-VNNI (the VEX form, on cores with AVX2 and no AVX-512, or with the kernels capped at
    /// 256 bits): 256-bit `VPDPBUSD`, blocks of 6 rows × 16 columns.
    AvxVnni,
    /// AVX2 without VNNI: 256-bit `VPMADDWD` on the bytes widened to 16 bits, pairs of inputs
    /// per i32 lane, blocks of 6 rows × 16 columns.
    Avx2Pairs,
    /// None of them: scalar roundings, only beside [`Tiles::Emulated`] (the tests on any core).
    Scalar,
}

/// Where the GEMMs run: the `VPDPBUSD` kernel of the [`Isa`], or AMX-INT8 tiles.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum Tiles {
    /// The `VPDPBUSD` kernel.
    None,
    /// `TDPBUSD` on the core's tiles.
    Amx,
    /// The tile kernel on tiles emulated in software.
    Emulated,
}

impl Tiles {
    /// Rows of the GEMMs' blocks: every tile's rows are padded to a multiple of it.
    fn mr(self) -> usize {
        match self {
            Tiles::None => MR,
            Tiles::Amx | Tiles::Emulated => amx::MR,
        }
    }

    /// A layer's inputs are padded to a multiple of this (a tile row holds 64 bytes).
    fn inputs(self) -> usize {
        match self {
            Tiles::None => GROUP,
            Tiles::Amx | Tiles::Emulated => 64,
        }
    }
}

// The tiles read the panels this module packs.
const _: () = assert!(NR == amx::I8_PANEL);

/// Whether this core has the 256-bit AVX-VNNI kernel's instructions.
pub fn avx_vnni_available() -> bool {
    #[cfg(target_arch = "x86_64")]
    {
        std::is_x86_feature_detected!("avx2")
            && std::is_x86_feature_detected!("fma")
            && std::is_x86_feature_detected!("avxvnni")
    }
    #[cfg(not(target_arch = "x86_64"))]
    {
        false
    }
}

/// Whether this core runs the 512-bit kernel.
pub fn native_available() -> bool {
    #[cfg(target_arch = "x86_64")]
    {
        std::is_x86_feature_detected!("avx512f")
            && std::is_x86_feature_detected!("avx512bw")
            && std::is_x86_feature_detected!("avx512vnni")
    }
    #[cfg(not(target_arch = "x86_64"))]
    {
        false
    }
}

/// A layer's weights (with its bias) packed for the one kernel that reads them.
#[derive(Debug, Clone)]
enum LayerWeights {
    /// `[panel][group][NR][4]` bytes: the `VPDPBUSD` kernels and the tiles.
    Bytes(Packed<u8>),
    /// `[panel][pair][NR][2]` in i16, the same values: [`Isa::Avx2Pairs`]'s `VPMADDWD` kernel.
    Pairs(Packed<i16>),
}

impl LayerWeights {
    /// `[panels × NR]`, zero past the outputs.
    fn bias(&self) -> &[f32] {
        match self {
            LayerWeights::Bytes(p) => &p.bias,
            LayerWeights::Pairs(p) => &p.bias,
        }
    }

    fn bias_mut(&mut self) -> &mut [f32] {
        match self {
            LayerWeights::Bytes(p) => &mut p.bias,
            LayerWeights::Pairs(p) => &mut p.bias,
        }
    }

    /// The inputs a row holds, padded (a multiple of [`GROUP`]).
    fn inputs(&self) -> usize {
        match self {
            LayerWeights::Bytes(p) => GROUP * p.groups,
            LayerWeights::Pairs(p) => PAIR * p.groups,
        }
    }
}

/// One layer in bytes: its weights and bias packed for the head's kernel, and each column's
/// scale.
#[derive(Debug, Clone)]
struct I8Layer {
    weights: LayerWeights,
    /// `[panels × NR]`, zero past the outputs.
    scales: Vec<f32>,
}

impl I8Layer {
    /// `dense` in bytes for `isa`, taking `padded_inputs` inputs (a multiple of 4; the extra ones
    /// weigh 0).
    fn of(dense: &Dense, padded_inputs: usize, isa: Isa) -> (I8Layer, Vec<i8>) {
        let (bytes, mut scales) = columns_to_i8(&dense.weight, dense.outputs);
        let as_values = Dense {
            weight: bytes.iter().map(|&b| b as f32).collect(),
            ..dense.clone()
        };
        let weights = if isa == Isa::Avx2Pairs {
            LayerWeights::Pairs(Packed::of(&as_values, padded_inputs, (PAIR, NR), |v| {
                v as i16
            }))
        } else {
            LayerWeights::Bytes(Packed::of(&as_values, padded_inputs, (GROUP, NR), |v| {
                v as i8 as u8
            }))
        };
        // Both packings have `outputs` rounded up to panels of `NR` (`Packed::of`).
        scales.resize(dense.outputs.div_ceil(NR) * NR, 0.0);
        (I8Layer { weights, scales }, bytes)
    }

    /// The rotation layer, reading encodings as `u = (e + 1)·127.5`:
    /// `Σ_i w_ij e_i = s_j · (Σ_i q_ij u_i) / 127.5 − s_j · Σ_i q_ij`; the second term joins the
    /// bias, the first's `1/127.5` is every row's scale.
    fn of_encoding(dense: &Dense, padded_inputs: usize, isa: Isa) -> I8Layer {
        let (mut layer, bytes) = I8Layer::of(dense, padded_inputs, isa);
        for (j, bias) in layer.weights.bias_mut()[..dense.outputs]
            .iter_mut()
            .enumerate()
        {
            let column: i32 = bytes
                .iter()
                .skip(j)
                .step_by(dense.outputs)
                .map(|&q| q as i32)
                .sum();
            *bias -= layer.scales[j] * column as f32;
        }
        layer
    }
}

/// One branch in bytes.
#[derive(Debug, Clone)]
struct I8Branch {
    hidden: Vec<I8Layer>,
    /// The output weights, zero-padded to the padded width.
    output: Vec<f32>,
    output_bias: f32,
}

/// The head on the 8-bit kernel.
#[derive(Debug, Clone)]
pub(super) struct I8Head {
    isa: Isa,
    tiles: Tiles,
    width: usize,
    /// Width rounded up to [`NR`]: the stride of every activation row.
    padded: usize,
    rotation: I8Layer,
    /// Length of a rotation's encoding.
    encoding: usize,
    branches: [I8Branch; 2],
}

/// One task's buffers: one f32 row, the encodings, a layer's f32 outputs, three byte buffers
/// (the shared input and two for the layers) with their rows' scales, the output dots, and a
/// GEMM's input widened to 16 bits ([`Isa::Avx2Pairs`]).
struct Scratch {
    row: Vec<f32>,
    e: Vec<u8>,
    /// Every encoded row's scale, `1/127.5`.
    e_scales: Vec<f32>,
    out: Vec<f32>,
    bytes: [Vec<u8>; 3],
    scales: [Vec<f32>; 3],
    dots: Vec<f32>,
    wide: Vec<u16>,
}

impl I8Head {
    /// Packs `head`'s weights in bytes for the widest kernel `kernels` allows and this core has
    /// (AVX-512 VNNI, else AVX-VNNI, else AVX2's `VPMADDWD`), or `None` when it has none of them
    /// or a branch has no hidden layer (or one of another width).
    pub(super) fn new(head: &HeadWeights, kernels: Kernels) -> Option<I8Head> {
        let (isa, tiles) = if kernels.allows_avx512() && native_available() {
            let amx = kernels.allows_amx() && amx::amx_int8_available();
            (Isa::Avx512, if amx { Tiles::Amx } else { Tiles::None })
        } else if kernels.allows_own() && avx_vnni_available() {
            (Isa::AvxVnni, Tiles::None)
        } else if kernels.allows_own() && avx2_available() {
            (Isa::Avx2Pairs, Tiles::None)
        } else {
            return None;
        };
        I8Head::packed(head, isa, tiles)
    }

    /// The `VPMADDWD` kernel on any core with AVX2 and FMA (whatever VNNI it has), or `None`
    /// as [`I8Head::new`]: for the tests.
    pub(super) fn avx2_pairs(head: &HeadWeights) -> Option<I8Head> {
        avx2_available()
            .then(|| I8Head::packed(head, Isa::Avx2Pairs, Tiles::None))
            .flatten()
    }

    /// The tile kernel on tiles emulated in software, on any core (its roundings on the widest
    /// vectors the core has): for the tests. `None` as [`I8Head::new`].
    pub(super) fn amx_emulated(head: &HeadWeights) -> Option<I8Head> {
        let isa = if native_available() {
            Isa::Avx512
        } else if avx_vnni_available() {
            Isa::AvxVnni
        } else {
            Isa::Scalar
        };
        I8Head::packed(head, isa, Tiles::Emulated)
    }

    /// `head` in bytes for `isa` and `tiles`.
    fn packed(head: &HeadWeights, isa: Isa, tiles: Tiles) -> Option<I8Head> {
        let width = head.width;
        let padded = width.div_ceil(NR) * NR;
        let branches = head
            .square_branches(padded)?
            .map(|(hidden, output, output_bias)| I8Branch {
                hidden: hidden
                    .iter()
                    .map(|d| I8Layer::of(d, padded, isa).0)
                    .collect(),
                output,
                output_bias,
            });
        let rotation = &head.rotation;
        Some(I8Head {
            isa,
            tiles,
            width,
            padded,
            rotation: I8Layer::of_encoding(
                rotation,
                rotation.inputs.next_multiple_of(tiles.inputs()),
                isa,
            ),
            encoding: rotation.inputs,
            branches,
        })
    }

    /// The kernel it runs on, in words.
    pub(super) fn kernel_name(&self) -> &'static str {
        match (self.tiles, self.isa) {
            (Tiles::Amx, _) => amx::KERNEL_NAME_I8,
            (Tiles::Emulated, _) => "AMX int8 tiles, emulated",
            (Tiles::None, Isa::Avx512) => "AVX-512 VNNI kernel",
            (Tiles::None, Isa::Avx2Pairs) => KERNEL_NAME_PAIRS,
            (Tiles::None, _) => "AVX-VNNI kernel (256-bit)",
        }
    }

    /// Whether it runs on the core's own instructions (not on emulated tiles).
    pub(super) fn is_native(&self) -> bool {
        self.tiles != Tiles::Emulated
    }

    /// The `branches`' log-weights of `rows` (0 for a branch left out), for one image's term of
    /// the first layer.
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
        let mut first_bias = self.rotation.weights.bias().to_vec();
        for (b, i) in first_bias.iter_mut().zip(image_term) {
            *b += i;
        }
        let mr = self.tiles.mr();
        let blocked = blocked_tile_rows(mr);
        let e_stride = self.rotation.weights.inputs();
        by_tiles(
            given,
            per_row,
            blocked,
            branches,
            || Scratch {
                row: vec![0.0; self.width],
                e: vec![0; blocked * e_stride],
                e_scales: vec![1.0 / ENCODING_SCALE; blocked],
                out: vec![0.0; blocked * self.padded],
                bytes: std::array::from_fn(|_| vec![0; blocked * self.padded]),
                scales: std::array::from_fn(|_| vec![0.0; blocked]),
                dots: vec![0.0; blocked],
                wide: match self.isa {
                    Isa::Avx2Pairs => vec![0; blocked * self.padded.max(e_stride)],
                    _ => Vec::new(),
                },
            },
            |scratch, given, out| {
                let tile = match rows {
                    Rows::Projected(_) => Rows::Projected(given),
                    Rows::Encoded(_) => Rows::Encoded(given),
                };
                // SAFETY: `new` checked the core's features for `isa`.
                unsafe {
                    match self.isa {
                        Isa::Avx512 => {
                            self.tile_avx512(image_term, &first_bias, tile, scratch, out)
                        }
                        Isa::AvxVnni => {
                            self.tile_avx_vnni(image_term, &first_bias, tile, scratch, out)
                        }
                        Isa::Avx2Pairs => {
                            self.tile_avx2(image_term, &first_bias, tile, scratch, out)
                        }
                        Isa::Scalar => self.tile(image_term, &first_bias, tile, scratch, out),
                    }
                }
            },
        )
    }

    /// [`I8Head::tile`] compiled for AVX-512, so that the rounding of rows to bytes between the
    /// GEMMs is vectorised to the kernel's width (narrower, it cost more than the GEMMs).
    ///
    /// # Safety
    /// The core has AVX-512F, BW and VNNI.
    #[cfg_attr(
        target_arch = "x86_64",
        target_feature(enable = "avx512f,avx512bw,avx512vnni")
    )]
    unsafe fn tile_avx512(
        &self,
        image_term: &[f32],
        first_bias: &[f32],
        given: Rows<'_>,
        scratch: &mut Scratch,
        out: &mut [&mut [f32]],
    ) {
        // SAFETY: the caller's contract.
        unsafe { self.tile(image_term, first_bias, given, scratch, out) }
    }

    /// [`I8Head::tile`] compiled for AVX2 and AVX-VNNI (no AVX-512 instruction in it).
    ///
    /// # Safety
    /// The core has AVX2, FMA and AVX-VNNI.
    #[cfg_attr(target_arch = "x86_64", target_feature(enable = "avx2,fma,avxvnni"))]
    unsafe fn tile_avx_vnni(
        &self,
        image_term: &[f32],
        first_bias: &[f32],
        given: Rows<'_>,
        scratch: &mut Scratch,
        out: &mut [&mut [f32]],
    ) {
        // SAFETY: the caller's contract.
        unsafe { self.tile(image_term, first_bias, given, scratch, out) }
    }

    /// [`I8Head::tile`] compiled for AVX2 and FMA (no VNNI instruction in it).
    ///
    /// # Safety
    /// The core has AVX2 and FMA.
    #[cfg_attr(target_arch = "x86_64", target_feature(enable = "avx2,fma"))]
    unsafe fn tile_avx2(
        &self,
        image_term: &[f32],
        first_bias: &[f32],
        given: Rows<'_>,
        scratch: &mut Scratch,
        out: &mut [&mut [f32]],
    ) {
        // SAFETY: the caller's contract.
        unsafe { self.tile(image_term, first_bias, given, scratch, out) }
    }

    /// One tile of rows: the shared input `relu(P_R + W_I·f + b)` in bytes, then each branch
    /// `out` holds an output for (the shape branch first).
    ///
    /// # Safety
    /// The core has the instructions of `self.isa`.
    #[inline(always)]
    unsafe fn tile(
        &self,
        image_term: &[f32],
        first_bias: &[f32],
        given: Rows<'_>,
        scratch: &mut Scratch,
        out: &mut [&mut [f32]],
    ) {
        let (w, stride) = (self.width, self.padded);
        let rows = out[0].len();
        let mr = self.tiles.mr();
        let blocked = rows.div_ceil(mr) * mr;
        // SAFETY: the caller's contract.
        unsafe { self.shared_input(image_term, first_bias, given, scratch, blocked) };
        let Scratch {
            out: values,
            bytes: [x, a, b],
            scales: [sx, sa, sb],
            dots,
            wide,
            ..
        } = scratch;
        for (branch, out) in self.branches.iter().zip(out.iter_mut()) {
            let last = branch.hidden.len() - 1;
            let dots = &mut dots[..blocked];
            dots.fill(branch.output_bias);
            for (l, layer) in branch.hidden.iter().enumerate() {
                // Layer l reads x (l = 0), a (odd l) or b, and writes the other of a and b.
                let (input, in_scales, output, out_scales) = match l {
                    0 => (&x[..], &sx[..], &mut a[..], &mut sa[..]),
                    l if l % 2 == 1 => (&a[..], &sa[..], &mut b[..], &mut sb[..]),
                    _ => (&b[..], &sb[..], &mut a[..], &mut sa[..]),
                };
                let bias = layer.weights.bias();
                let input = Input {
                    bytes: input,
                    scales: in_scales,
                    stride,
                };
                if l == last {
                    let dot = Epilogue::Dot {
                        weights: &branch.output,
                        dots: &mut *dots,
                    };
                    // SAFETY: as above; `input` holds `blocked` rows of `stride`.
                    unsafe { self.gemm(layer, bias, input, blocked, dot, wide) };
                } else {
                    let store = Epilogue::Store {
                        out: &mut values[..],
                        stride,
                    };
                    // SAFETY: as above.
                    unsafe { self.gemm(layer, bias, input, blocked, store, wide) };
                    rows_to_u8(self.isa, values, output, out_scales, blocked, (w, stride));
                }
            }
            out.copy_from_slice(&dots[..rows]);
        }
    }

    /// The shared input of a tile's `blocked` rows in bytes, into `scratch.bytes[0]` with its
    /// rows' scales: from projections, `relu(P_R + W_I·f + b)` rounded per row; from
    /// encodings, the rotation layer on their bytes, then rounded per row.
    ///
    /// # Safety
    /// The core has the instructions of `self.isa`.
    #[inline(always)]
    unsafe fn shared_input(
        &self,
        image_term: &[f32],
        first_bias: &[f32],
        given: Rows<'_>,
        scratch: &mut Scratch,
        blocked: usize,
    ) {
        let (w, stride) = (self.width, self.padded);
        let Scratch {
            row,
            e,
            e_scales,
            out: values,
            bytes: [x, ..],
            scales: [sx, ..],
            wide,
            ..
        } = scratch;
        match given {
            Rows::Projected(projected) => {
                x[..blocked * stride].fill(0);
                sx[..blocked].fill(0.0);
                for (r, pr) in projected.chunks_exact(w).enumerate() {
                    for ((v, &p), &i) in row.iter_mut().zip(pr).zip(image_term) {
                        *v = (p + i).max(0.0);
                    }
                    sx[r] = row_bytes(self.isa, row, &mut x[r * stride..r * stride + w]);
                }
            }
            Rows::Encoded(encodings) => {
                let e_stride = self.rotation.weights.inputs();
                e[..blocked * e_stride].fill(0);
                for (er, enc) in e
                    .chunks_exact_mut(e_stride)
                    .zip(encodings.chunks_exact(self.encoding))
                {
                    encoding_bytes(self.isa, enc, er);
                }
                let store = Epilogue::Store {
                    out: &mut values[..],
                    stride,
                };
                let input = Input {
                    bytes: e,
                    scales: e_scales,
                    stride: e_stride,
                };
                // SAFETY: the core has the kernel's features (the caller's contract); `e` holds
                // `blocked` rows of `e_stride` = 4 × groups, `e_scales` and the output
                // `blocked` rows, `first_bias` the layer's panels × NR values.
                unsafe { self.gemm(&self.rotation, first_bias, input, blocked, store, wide) };
                rows_to_u8(self.isa, values, x, sx, blocked, (w, stride));
            }
        }
    }

    /// [`gemm`] on the head's tiles, or its `VPDPBUSD` kernel, or (for [`Isa::Avx2Pairs`]) its
    /// input widened into `wide` and the `VPMADDWD` kernel.
    ///
    /// # Safety
    /// As [`gemm`] (`rows` a multiple of `self.tiles.mr()`), and the core has what
    /// [`I8Head::new`] checked; for [`Isa::Avx2Pairs`], `wide` holds `rows × input.stride`.
    #[inline(always)]
    unsafe fn gemm(
        &self,
        layer: &I8Layer,
        bias: &[f32],
        input: Input<'_>,
        rows: usize,
        epilogue: Epilogue<'_, f32>,
        wide: &mut [u16],
    ) {
        let scales = BytesScales {
            bias,
            columns: &layer.scales,
            rows: input.scales,
        };
        let bytes = (input.bytes, input.stride);
        // SAFETY: the caller's contract; layers were packed with inputs padded to 64 bytes for
        // the tiles.
        unsafe {
            match (self.tiles, &layer.weights) {
                #[cfg(target_arch = "x86_64")]
                (Tiles::Amx, LayerWeights::Bytes(packed)) => {
                    amx::gemm_i8_amx(packed, scales, bytes, rows, epilogue)
                }
                #[cfg(not(target_arch = "x86_64"))]
                (Tiles::Amx, _) => unreachable!("AMX is only built on x86_64"),
                (Tiles::Emulated, LayerWeights::Bytes(packed)) => {
                    amx::gemm_i8_emulated(packed, scales, bytes, rows, epilogue)
                }
                (Tiles::None, LayerWeights::Pairs(pairs)) => {
                    let n = rows * input.stride;
                    for (w, &b) in wide[..n].iter_mut().zip(&input.bytes[..n]) {
                        *w = b as u16;
                    }
                    let input = Input {
                        bytes: &wide[..n],
                        scales: input.scales,
                        stride: input.stride,
                    };
                    gemm_pairs(pairs, &layer.scales, bias, input, rows, epilogue)
                }
                (Tiles::None, LayerWeights::Bytes(packed)) => {
                    gemm(self.isa, packed, &layer.scales, bias, input, rows, epilogue)
                }
                (_, LayerWeights::Pairs(_)) => {
                    unreachable!("pairs are packed only for the kernel without tiles")
                }
            }
        }
    }
}

/// The first `rows` rows of `values` (`width` values each, rows `stride` apart) in bytes on
/// their own grids ([`row_to_u8`]), into `bytes` and `scales`.
#[inline(always)]
fn rows_to_u8(
    isa: Isa,
    values: &[f32],
    bytes: &mut [u8],
    scales: &mut [f32],
    rows: usize,
    (width, stride): (usize, usize),
) {
    for (r, scale) in scales[..rows].iter_mut().enumerate() {
        let at = r * stride;
        *scale = row_bytes(isa, &values[at..at + width], &mut bytes[at..at + width]);
    }
}

/// [`encoding_to_u8`] of each of `src` into `dst`, 16 values per instruction where the length
/// allows (the same clamp and product, rounded to nearest even by `VCVTPS2UDQ`).
#[inline(always)]
fn encoding_bytes(isa: Isa, src: &[f32], dst: &mut [u8]) {
    let mut done = 0;
    #[cfg(target_arch = "x86_64")]
    if isa == Isa::Avx512 && native_available() {
        done = src.len().min(dst.len()) / 16 * 16;
        // SAFETY: the features were checked; both slices hold `done` values.
        unsafe { encoding_bytes_avx512(&src[..done], &mut dst[..done]) };
    } else if matches!(isa, Isa::AvxVnni | Isa::Avx2Pairs) && avx2_available() {
        done = src.len().min(dst.len()) / 8 * 8;
        // SAFETY: as above.
        unsafe { encoding_bytes_avx2(&src[..done], &mut dst[..done]) };
    }
    for (d, &e) in dst.iter_mut().zip(src).skip(done) {
        *d = encoding_to_u8(e);
    }
}

/// # Safety
/// The core has AVX-512F; `src.len()` is a multiple of 16 and at most `dst.len()`.
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx512f")]
unsafe fn encoding_bytes_avx512(src: &[f32], dst: &mut [u8]) {
    use std::arch::x86_64::*;
    let (one, two) = (_mm512_set1_ps(1.0), _mm512_set1_ps(2.0));
    let (zero, scale) = (_mm512_setzero_ps(), _mm512_set1_ps(ENCODING_SCALE));
    for (v, d) in src.chunks_exact(16).zip(dst.chunks_exact_mut(16)) {
        // SAFETY: 16 floats read, 16 bytes written.
        unsafe {
            let e = _mm512_add_ps(_mm512_loadu_ps(v.as_ptr()), one);
            let u = _mm512_mul_ps(_mm512_min_ps(_mm512_max_ps(e, zero), two), scale);
            let bytes = _mm512_cvtepi32_epi8(_mm512_cvtps_epu32(u));
            _mm_storeu_si128(d.as_mut_ptr() as *mut __m128i, bytes);
        }
    }
}

/// [`row_to_u8`], 16 values per instruction where the width allows: the same maximum, the same
/// products, rounded to nearest even by `VCVTPS2UDQ` as by the scalar version.
#[inline(always)]
fn row_bytes(isa: Isa, src: &[f32], dst: &mut [u8]) -> f32 {
    #[cfg(target_arch = "x86_64")]
    if isa == Isa::Avx512
        && src.len().is_multiple_of(16)
        && dst.len() >= src.len()
        && native_available()
    {
        // SAFETY: the features were checked; `src` holds whole vectors, `dst` as many bytes.
        return unsafe { row_bytes_avx512(src, dst) };
    }
    #[cfg(target_arch = "x86_64")]
    if matches!(isa, Isa::AvxVnni | Isa::Avx2Pairs)
        && src.len().is_multiple_of(8)
        && dst.len() >= src.len()
        && avx2_available()
    {
        // SAFETY: as above, with 8-lane vectors.
        return unsafe { row_bytes_avx2(src, dst) };
    }
    row_to_u8(src, dst)
}

/// # Safety
/// The core has AVX-512F; `src.len()` is a multiple of 16 and at most `dst.len()`.
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx512f")]
unsafe fn row_bytes_avx512(src: &[f32], dst: &mut [u8]) -> f32 {
    use std::arch::x86_64::*;
    // SAFETY: whole vectors of `src` read, as many bytes of `dst` written.
    unsafe {
        let mut max = _mm512_setzero_ps();
        for v in src.chunks_exact(16) {
            max = _mm512_max_ps(_mm512_loadu_ps(v.as_ptr()), max);
        }
        let max = _mm512_reduce_max_ps(max);
        if !(max > 0.0 && max.is_finite()) {
            return row_to_u8(src, dst);
        }
        let inverse = _mm512_set1_ps(255.0 / max);
        let (low, high) = (_mm512_setzero_ps(), _mm512_set1_ps(255.0));
        for (v, d) in src.chunks_exact(16).zip(dst.chunks_exact_mut(16)) {
            let x = _mm512_mul_ps(_mm512_loadu_ps(v.as_ptr()), inverse);
            let x = _mm512_min_ps(_mm512_max_ps(x, low), high);
            let bytes = _mm512_cvtepi32_epi8(_mm512_cvtps_epu32(x));
            _mm_storeu_si128(d.as_mut_ptr() as *mut __m128i, bytes);
        }
        max / 255.0
    }
}

/// Eight i32 in 0..=255 as eight bytes at `dst`.
///
/// # Safety
/// The core has AVX2; `dst` points at 8 writable bytes.
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2")]
unsafe fn store_8_bytes(v: std::arch::x86_64::__m256i, dst: *mut u8) {
    use std::arch::x86_64::*;
    let words = _mm_packus_epi32(_mm256_castsi256_si128(v), _mm256_extracti128_si256(v, 1));
    // SAFETY: 8 bytes written.
    unsafe { _mm_storel_epi64(dst as *mut __m128i, _mm_packus_epi16(words, words)) };
}

/// [`encoding_to_u8`] 8 at a time on AVX2 (`VCVTPS2DQ` rounds to nearest even).
///
/// # Safety
/// The core has AVX2; `src.len()` is a multiple of 8 and at most `dst.len()`.
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2")]
unsafe fn encoding_bytes_avx2(src: &[f32], dst: &mut [u8]) {
    use std::arch::x86_64::*;
    let (one, two) = (_mm256_set1_ps(1.0), _mm256_set1_ps(2.0));
    let (zero, scale) = (_mm256_setzero_ps(), _mm256_set1_ps(ENCODING_SCALE));
    for (v, d) in src.chunks_exact(8).zip(dst.chunks_exact_mut(8)) {
        // SAFETY: 8 floats read, 8 bytes written.
        unsafe {
            let e = _mm256_add_ps(_mm256_loadu_ps(v.as_ptr()), one);
            let u = _mm256_mul_ps(_mm256_min_ps(_mm256_max_ps(e, zero), two), scale);
            store_8_bytes(_mm256_cvtps_epi32(u), d.as_mut_ptr());
        }
    }
}

/// [`row_to_u8`] 8 at a time on AVX2.
///
/// # Safety
/// The core has AVX2; `src.len()` is a multiple of 8 and at most `dst.len()`.
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2")]
unsafe fn row_bytes_avx2(src: &[f32], dst: &mut [u8]) -> f32 {
    use std::arch::x86_64::*;
    // SAFETY: whole vectors of `src` read, as many bytes of `dst` written.
    unsafe {
        let mut max = _mm256_setzero_ps();
        for v in src.chunks_exact(8) {
            max = _mm256_max_ps(_mm256_loadu_ps(v.as_ptr()), max);
        }
        let mut lanes = [0f32; 8];
        _mm256_storeu_ps(lanes.as_mut_ptr(), max);
        let max = lanes.iter().fold(0f32, |m, &v| m.max(v));
        if !(max > 0.0 && max.is_finite()) {
            return row_to_u8(src, dst);
        }
        let inverse = _mm256_set1_ps(255.0 / max);
        let (low, high) = (_mm256_setzero_ps(), _mm256_set1_ps(255.0));
        for (v, d) in src.chunks_exact(8).zip(dst.chunks_exact_mut(8)) {
            let x = _mm256_mul_ps(_mm256_loadu_ps(v.as_ptr()), inverse);
            let x = _mm256_min_ps(_mm256_max_ps(x, low), high);
            store_8_bytes(_mm256_cvtps_epi32(x), d.as_mut_ptr());
        }
        max / 255.0
    }
}

/// A GEMM's input: `rows` rows of bytes (or of bytes widened to 16 bits) `stride` apart, each
/// with its scale.
#[derive(Clone, Copy)]
struct Input<'a, E = u8> {
    bytes: &'a [E],
    scales: &'a [f32],
    stride: usize,
}

/// `relu(acc · s_row · s_col + b)` of `rows` rows of `input` times `layer`, through `epilogue`:
/// the GEMM on `VPDPBUSD` of `isa`.
///
/// # Safety
/// The core has `isa`'s instructions (when it does not, this is never called); `rows` is a
/// multiple of [`MR`]; `input` holds `rows × stride` bytes with `stride ≥ 4 × groups` and
/// `rows` scales; `bias` the layer's `panels × NR`; a `Store` output holds `rows` rows of its
/// stride (≥ panels × NR), a `Dot` `rows` dots and `panels × NR` weights.
unsafe fn gemm(
    isa: Isa,
    packed: &Packed<u8>,
    scales: &[f32],
    bias: &[f32],
    input: Input<'_>,
    rows: usize,
    epilogue: Epilogue<'_, f32>,
) {
    debug_assert!(
        rows.is_multiple_of(MR)
            && input.bytes.len() >= rows * input.stride
            && input.stride >= GROUP * packed.groups
            && input.scales.len() >= rows
            && bias.len() >= packed.panels * NR
            && scales.len() >= packed.panels * NR
    );
    #[cfg(target_arch = "x86_64")]
    // SAFETY: the caller's contract is the kernels'.
    unsafe {
        match isa {
            Isa::Avx512 => gemm_avx512(packed, scales, bias, input, rows, epilogue),
            Isa::AvxVnni => gemm_avx_vnni(packed, scales, bias, input, rows, epilogue),
            Isa::Avx2Pairs => unreachable!("the pairs kernel reads widened input (`gemm_pairs`)"),
            Isa::Scalar => unreachable!("the scalar roundings run only beside emulated tiles"),
        }
    }
    #[cfg(not(target_arch = "x86_64"))]
    {
        let _ = (isa, packed, scales, bias, input, rows, epilogue);
        unreachable!("the native kernels are only built on x86_64")
    }
}

/// [`gemm`] on [`Isa::Avx2Pairs`]: `input` the bytes widened to 16 bits, `pairs` the layer's
/// weights in 16-bit pairs, `scales` its columns' scales.
///
/// # Safety
/// As [`gemm`], with pairs for groups; the core has AVX2 and FMA.
unsafe fn gemm_pairs(
    pairs: &Packed<i16>,
    scales: &[f32],
    bias: &[f32],
    input: Input<'_, u16>,
    rows: usize,
    epilogue: Epilogue<'_, f32>,
) {
    debug_assert!(
        rows.is_multiple_of(MR)
            && input.bytes.len() >= rows * input.stride
            && input.stride >= PAIR * pairs.groups
            && input.scales.len() >= rows
            && bias.len() >= pairs.panels * NR
            && scales.len() >= pairs.panels * NR
    );
    #[cfg(target_arch = "x86_64")]
    // SAFETY: the caller's contract is the kernel's.
    unsafe {
        gemm_avx2_pairs(pairs, scales, bias, input, rows, epilogue)
    }
    #[cfg(not(target_arch = "x86_64"))]
    {
        let _ = (pairs, scales, bias, input, rows, epilogue);
        unreachable!("the native kernels are only built on x86_64")
    }
}

/// `acc + VPMADDWD(x, w)`: each i32 lane of `acc` plus its two 16-bit products (exact: the
/// inputs are bytes, so no pair's sum nears the i32 range).
///
/// # Safety
/// The core has AVX2.
#[cfg(target_arch = "x86_64")]
#[inline]
#[target_feature(enable = "avx2")]
unsafe fn madd_pairs(
    acc: std::arch::x86_64::__m256i,
    x: std::arch::x86_64::__m256i,
    w: std::arch::x86_64::__m256i,
) -> std::arch::x86_64::__m256i {
    use std::arch::x86_64::*;
    _mm256_add_epi32(acc, _mm256_madd_epi16(x, w))
}

/// A [`gemm`] on one vector width: each 64-column panel in blocks of `MR` rows × `NV` vectors
/// of `LANES` i32 lanes; each row's `LANE_INPUTS` inputs of a group (four bytes, or two 16-bit values)
/// broadcast from the row, the block's weights of a group loaded once;
/// `relu(acc · s_row · s_col + b)` (or the output dot product) as each block leaves the
/// registers. `$hsum` sums a vector's lanes.
///
/// As the f32 kernels (`net::native`), the common input strides (the padded widths 128, 256
/// and 512) run an instance with the stride a constant, so each row's broadcast is one load at
/// a fixed displacement from the block: no address arithmetic between the multiplies. (With
/// the stride in a register, 5 of the `VPMADDWD` loop's 41 instructions computed row addresses
/// on AMD Zen 3, whose dispatch width the loop fills; 36 with it a constant. Four or two groups
/// a trip, as the f32 kernels run, made the compiler spill accumulators or branch within the
/// trip here; docs/BENCHMARKS.md.)
macro_rules! vnni_gemm {
    ($(#[$doc:meta])* $name:ident, $feature:literal, $elem:ty, $weight:ty, group $group:expr,
     lanes $lanes:literal, nv $nv:literal,
     $vi:ty, $zero_i:ident, $load_i:ident, $set1_i:ident, $dpbusd:ident,
     $vf:ty, $zero:ident, $load:ident, $store:ident, $set1:ident, $cvt:ident, $fmadd:ident,
     $mul:ident, $max:ident, $hsum:path) => {
        $(#[$doc])*
        ///
        /// # Safety
        /// As [`gemm`], with the target features named.
        #[cfg(target_arch = "x86_64")]
        #[target_feature(enable = $feature)]
        unsafe fn $name(
            packed: &Packed<$weight>,
            scales: &[f32],
            bias: &[f32],
            input: Input<'_, $elem>,
            rows: usize,
            epilogue: Epilogue<'_, f32>,
        ) {
            #[target_feature(enable = $feature)]
            unsafe fn by_stride<const STRIDE: usize>(
                packed: &Packed<$weight>,
                scales: &[f32],
                bias: &[f32],
                input: Input<'_, $elem>,
                rows: usize,
                epilogue: Epilogue<'_, f32>,
            ) {
                use std::arch::x86_64::*;
                const NV: usize = $nv;
                const COLUMNS: usize = $lanes * NV;
                const LANE_INPUTS: usize = $group;
                let stride = if STRIDE == 0 { input.stride } else { STRIDE };
                let groups = packed.groups;
                let mut epilogue = epilogue;
                for panel in 0..packed.panels {
                    for block in 0..NR / COLUMNS {
                        let column = panel * NR + COLUMNS * block;
                        // SAFETY (all pointer reads and writes below): within the bounds of
                        // `gemm`'s contract; a block's weights are its columns' bytes of each group.
                        unsafe {
                            let weights = packed.weight.as_ptr().add(
                                panel * groups * NR * LANE_INPUTS + COLUMNS * block * LANE_INPUTS,
                            );
                            let at = |v: &[f32], c: usize| $load(v.as_ptr().add(column + $lanes * c));
                            let bias: [$vf; NV] = std::array::from_fn(|c| at(bias, c));
                            let scale: [$vf; NV] = std::array::from_fn(|c| at(scales, c));
                            for r0 in (0..rows).step_by(MR) {
                                let mut acc = [[$zero_i(); NV]; MR];
                                let a = input.bytes.as_ptr().add(r0 * stride);
                                for g in 0..groups {
                                    let w = weights.add(g * NR * LANE_INPUTS);
                                    let b: [$vi; NV] = std::array::from_fn(|c| {
                                        $load_i(w.add(LANE_INPUTS * $lanes * c) as *const _)
                                    });
                                    let x = a.add(LANE_INPUTS * g);
                                    for (r, acc) in acc.iter_mut().enumerate() {
                                        let inputs =
                                            (x.add(r * stride) as *const i32).read_unaligned();
                                        let x = $set1_i(inputs);
                                        for c in 0..NV {
                                            acc[c] = $dpbusd(acc[c], x, b[c]);
                                        }
                                    }
                                }
                                let zero = $zero();
                                for (r, acc) in acc.iter().enumerate() {
                                    let row = r0 + r;
                                    let s = $set1(input.scales[row]);
                                    let h: [$vf; NV] = std::array::from_fn(|c| {
                                        let scaled = $fmadd($cvt(acc[c]), $mul(scale[c], s), bias[c]);
                                        $max(scaled, zero)
                                    });
                                    match &mut epilogue {
                                        Epilogue::Store { out, stride } => {
                                            let o = out.as_mut_ptr().add(row * *stride + column);
                                            for (c, h) in h.iter().enumerate() {
                                                $store(o.add($lanes * c), *h);
                                            }
                                        }
                                        Epilogue::Dot { weights, dots } => {
                                            let w = weights.as_ptr().add(column);
                                            let mut sum = $mul(h[0], $load(w));
                                            for (c, h) in h.iter().enumerate().skip(1) {
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
            }
            // SAFETY: the caller's contract; each instance reads `input.stride` as given.
            unsafe {
                with_constant_stride!(
                    input.stride,
                    by_stride(packed, scales, bias, input, rows, epilogue)
                )
            }
        }
    };
}

vnni_gemm!(
    /// [`gemm`] on AVX-512 VNNI: blocks of 6 rows × 64 columns (24 i32 accumulators).
    gemm_avx512, "avx512f,avx512bw,avx512vnni", u8, u8, group GROUP, lanes 16, nv 4,
    __m512i, _mm512_setzero_si512, _mm512_loadu_si512, _mm512_set1_epi32, _mm512_dpbusd_epi32,
    __m512, _mm512_setzero_ps, _mm512_loadu_ps, _mm512_storeu_ps, _mm512_set1_ps,
    _mm512_cvtepi32_ps, _mm512_fmadd_ps, _mm512_mul_ps, _mm512_max_ps, _mm512_reduce_add_ps
);

vnni_gemm!(
    /// [`gemm`] on AVX-VNNI: blocks of 6 rows × 16 columns (12 i32 accumulators, two weight
    /// vectors and a broadcast in the 16 ymm registers).
    gemm_avx_vnni, "avx2,fma,avxvnni", u8, u8, group GROUP, lanes 8, nv 2,
    __m256i, _mm256_setzero_si256, _mm256_loadu_si256, _mm256_set1_epi32,
    _mm256_dpbusd_avx_epi32,
    __m256, _mm256_setzero_ps, _mm256_loadu_ps, _mm256_storeu_ps, _mm256_set1_ps,
    _mm256_cvtepi32_ps, _mm256_fmadd_ps, _mm256_mul_ps, _mm256_max_ps, super::native::hsum256
);

vnni_gemm!(
    /// [`gemm_pairs`] on AVX2: blocks of 6 rows × 16 columns (12 i32 accumulators, two weight
    /// vectors, a broadcast and a product in the 16 ymm registers), each lane two 16-bit inputs.
    gemm_avx2_pairs, "avx2,fma", u16, i16, group PAIR, lanes 8, nv 2,
    __m256i, _mm256_setzero_si256, _mm256_loadu_si256, _mm256_set1_epi32, madd_pairs,
    __m256, _mm256_setzero_ps, _mm256_loadu_ps, _mm256_storeu_ps, _mm256_set1_ps,
    _mm256_cvtepi32_ps, _mm256_fmadd_ps, _mm256_mul_ps, _mm256_max_ps, super::native::hsum256
);

#[cfg(test)]
mod tests {
    use super::*;

    /// The vector rounding of a row (and of encodings) to bytes gives the scalar one's bytes, ties (a
    /// product exactly halfway between two bytes) included, and so does a row of zeros.
    #[test]
    fn rows_round_to_the_same_bytes_in_vectors_as_in_scalars() {
        let mut rows: Vec<Vec<f32>> = (0..20)
            .map(|r| {
                (0..64)
                    .map(|i| (((i * 37 + r * 11) % 23) as f32 * 0.37 - 2.0).max(0.0))
                    .collect()
            })
            .collect();
        // Steps of 1 up to the maximum 255, and halves between them: ties.
        rows.push((0..64).map(|i| (i % 32) as f32 * 0.5).collect::<Vec<f32>>());
        rows.last_mut().unwrap()[63] = 255.0;
        rows.push(vec![0.0; 64]);
        for isa in [Isa::Avx512, Isa::AvxVnni, Isa::Avx2Pairs] {
            for row in &rows {
                let (mut vector, mut scalar) = ([0u8; 64], [0u8; 64]);
                let step = row_bytes(isa, row, &mut vector);
                assert_eq!(step, row_to_u8(row, &mut scalar));
                assert_eq!(vector, scalar, "{isa:?} {row:?}");
            }
        }
        // Encodings: every value of [−1, 1] in steps that fall on and between the bytes.
        let encodings: Vec<f32> = (0..=1020).map(|i| i as f32 / 510.0 - 1.0).collect();
        let scalar: Vec<u8> = encodings.iter().map(|&e| encoding_to_u8(e)).collect();
        for isa in [Isa::Avx512, Isa::AvxVnni, Isa::Avx2Pairs] {
            let mut vector = vec![0u8; 1021];
            encoding_bytes(isa, &encodings, &mut vector);
            assert_eq!(vector, scalar, "{isa:?}");
        }
        let mut bytes = [0u8; 64];
        row_bytes(Isa::Avx512, &rows[20], &mut bytes);
        // 0.5 → 0, 1.5 → 2, 2.5 → 2: to even, as VCVTPS2UDQ rounds.
        assert_eq!((bytes[1], bytes[3], bytes[5]), (0, 2, 2));
    }

    /// A column's largest |w| is ±127 and the rest keep their ratio to it within half a step.
    #[test]
    fn each_column_has_its_own_scale() {
        // Two columns, the second a thousand times larger than the first.
        let weight = [0.5, 400.0, -1.0, 250.0, 0.25, -1000.0];
        let (bytes, scales) = columns_to_i8(&weight, 2);
        assert_eq!(bytes, [64, 51, -127, 32, 32, -127]);
        assert_eq!(scales, [1.0 / 127.0, 1000.0 / 127.0]);
    }
}
