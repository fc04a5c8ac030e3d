//! The dual-branch head for inference, fused (paper Sec. 3.3, Eq. 6's `s_θ` and `s_φ`): the
//! same weights as [`DualHead`], read once into plain row-major matrices, evaluated in row tiles
//! that stay in the core's cache. For each tile of rotations: `x = relu(P_R + W_I·f + b)` (the
//! rotation projections `P_R` precomputed per grid level), then per branch three
//! `h ← relu(h·W + b)` GEMMs (the project's kernels of [`super::native`], else the library GEMM
//! of `net::dense`; one thread per tile, tiles spread over the cores) with bias and ReLU applied to the tile in place, and the last `256 → 1` layer
//! as a dot product. No intermediate leaves the tile, so the head runs near the library's matmul
//! peak. The burn network stays the reference (training, tests).

use rayon::prelude::*;

use super::DualHead;
use super::amx::{AmxBf16, EmulatedAmxBf16};
use super::bf16::Bf16Kernel;
use super::dense;
use super::f16::F16Kernel;
use super::i8::I8Head;
use super::kernels::Kernels;
use super::native::{F32Avx2, F32Avx512, NativeHead};
use super::tiles::{Branches, by_tiles, round_bf16, round_encoding_u8, round_f16, round_rows_u8};
pub use super::tiles::{Precision, Rows, TILE_ROWS, tile_rows};
use super::weights::HeadWeights;

/// The rounding of a reduced precision's weights (per value) and encodings (the identity for
/// f32 and for the 8-bit head's weights, which [`HeadWeights::quantized_i8`] rounds by column).
fn rounding(precision: Precision) -> fn(f32) -> f32 {
    match precision {
        Precision::F32 => std::convert::identity,
        Precision::Bf16 => round_bf16,
        Precision::F16 => round_f16,
        Precision::I8 => round_encoding_u8,
    }
}

/// Rows of `width` activations rounded as `precision`'s kernel reads them: per value in
/// bfloat16 and f16, on each row's 8-bit grid in i8.
fn round_activations(precision: Precision, values: &mut [f32], width: usize) {
    match precision {
        Precision::F32 => {}
        Precision::I8 => round_rows_u8(values, width),
        _ => {
            let round = rounding(precision);
            values.iter_mut().for_each(|v| *v = round(*v));
        }
    }
}

/// `max(v, 0)` that keeps NaN (`f32::max` would return 0): a reduced-precision row that
/// overflowed must stay non-finite, so that it is scored again in f32.
fn relu(x: &mut [f32]) {
    for v in x {
        if *v < 0.0 {
            *v = 0.0;
        }
    }
}

/// The head on one of the project's f32 kernels.
#[derive(Debug, Clone)]
enum F32Native {
    Avx512(NativeHead<F32Avx512>),
    Avx2(NativeHead<F32Avx2>),
}

impl F32Native {
    /// The widest f32 kernel `kernels` allows and the core has, if any.
    fn new(head: &HeadWeights, kernels: Kernels) -> Option<F32Native> {
        let avx512 = kernels
            .allows_avx512()
            .then(|| NativeHead::new(head).map(F32Native::Avx512))
            .flatten();
        avx512.or_else(|| {
            kernels
                .allows_own()
                .then(|| NativeHead::new(head).map(F32Native::Avx2))
                .flatten()
        })
    }

    fn name(&self) -> &'static str {
        match self {
            F32Native::Avx512(_) => "AVX-512F kernel",
            F32Native::Avx2(_) => "AVX2 kernel",
        }
    }

    fn branch_scores(
        &self,
        image_term: &[f32],
        rows: Rows<'_>,
        branches: Branches,
    ) -> (Vec<f32>, Vec<f32>) {
        match self {
            F32Native::Avx512(h) => h.branch_scores(image_term, rows, branches),
            F32Native::Avx2(h) => h.branch_scores(image_term, rows, branches),
        }
    }
}

/// The fused inference head.
#[derive(Debug, Clone)]
pub struct FusedHead {
    weights: HeadWeights,
    /// Round every GEMM's input to this precision (the emulation of a [`ReducedHead`]; `F32`:
    /// no rounding).
    rounds_to: Precision,
    /// The kernels allowed, also for the library GEMM of the portable path.
    kernels: Kernels,
    /// The same head in bfloat16, in f16 and in 8-bit integers (`None` in an emulation itself).
    bf16: Option<Box<ReducedHead>>,
    f16: Option<Box<ReducedHead>>,
    i8: Option<Box<ReducedHead>>,
    /// The same head on the f32 512-bit kernel, where the core has it and the kernels allowed
    /// (`None` in the emulation).
    f32_native: Option<Box<F32Native>>,
}

/// A tile's scratch: the branch input and two activation buffers.
struct Scratch {
    x: Vec<f32>,
    a: Vec<f32>,
    b: Vec<f32>,
}

impl FusedHead {
    /// Reads `head`'s weights, for the kernels [`Kernels::from_env`] allows.
    pub fn new(head: &DualHead) -> FusedHead {
        FusedHead::with_kernels(head, Kernels::from_env())
    }

    /// Reads `head`'s weights, for `kernels`.
    pub fn with_kernels(head: &DualHead, kernels: Kernels) -> FusedHead {
        let weights = HeadWeights::of(head);
        FusedHead {
            bf16: Some(Box::new(ReducedHead::new(
                &weights,
                Precision::Bf16,
                kernels,
            ))),
            f16: Some(Box::new(ReducedHead::new(
                &weights,
                Precision::F16,
                kernels,
            ))),
            i8: Some(Box::new(ReducedHead::new(&weights, Precision::I8, kernels))),
            f32_native: F32Native::new(&weights, kernels).map(Box::new),
            weights,
            rounds_to: Precision::F32,
            kernels,
        }
    }

    /// This head with the branches' and the rotation layer's weights rounded to `precision` and
    /// each GEMM's input (encodings included) rounded too: the emulation of a [`ReducedHead`] on
    /// the f32 GEMM. The image half of the first layer stays f32, as in the native kernels, and
    /// so do projections made beforehand by the f32 head (a search's start level).
    fn rounded_to(weights: &HeadWeights, precision: Precision, kernels: Kernels) -> FusedHead {
        let weights = match precision {
            Precision::I8 => weights.quantized_i8(),
            _ => weights.rounded_by(rounding(precision)),
        };
        FusedHead {
            weights,
            rounds_to: precision,
            kernels,
            bf16: None,
            f16: None,
            i8: None,
            f32_native: None,
        }
    }

    /// The head in a reduced precision, if this head has one (not in an emulation).
    fn reduced(&self, precision: Precision) -> Option<&ReducedHead> {
        match precision {
            Precision::F32 => None,
            Precision::Bf16 => self.bf16.as_deref(),
            Precision::F16 => self.f16.as_deref(),
            Precision::I8 => self.i8.as_deref(),
        }
    }

    /// Whether `precision` runs on the core's own instructions for it: always for f32 (the
    /// project's kernels or the library GEMM); for bfloat16 and f16 where the core has AVX-512
    /// BF16 or FP16 (else they are emulated on the f32 GEMM, at the f32 rate).
    pub fn native(&self, precision: Precision) -> bool {
        precision == Precision::F32 || self.reduced(precision).is_some_and(|r| r.is_native())
    }

    /// The kernel a reduced `precision` runs on, in words (f32's: [`FusedHead::kernel_paths`]).
    pub fn kernel_name(&self, precision: Precision) -> &'static str {
        self.reduced(precision)
            .map_or("emulated on the f32 GEMM", ReducedHead::kernel_name)
    }

    /// Whether [`Precision::F32`] runs on one of the project's kernels (else on the library GEMM).
    pub fn f32_native(&self) -> bool {
        self.f32_native.is_some()
    }

    /// The kernel each precision runs on, in words (for logs and the bench).
    pub fn kernel_paths(&self) -> String {
        let reduced = |precision: Precision| self.kernel_name(precision);
        format!(
            "f32: {}, bf16: {}, f16: {}, i8: {}",
            self.f32_native
                .as_ref()
                .map_or(dense::library_name(self.kernels), |k| k.name()),
            reduced(Precision::Bf16),
            reduced(Precision::F16),
            reduced(Precision::I8),
        )
    }

    /// Width of the hidden layers.
    pub fn width(&self) -> usize {
        self.weights.width
    }

    /// Length of the image features the head takes.
    pub fn image_dim(&self) -> usize {
        self.weights.image.inputs
    }

    /// Length of the rotation encoding the head takes.
    pub fn rotation_dim(&self) -> usize {
        self.weights.rotation.inputs
    }

    /// The image half of the first layer, `W_I·f + b_I`, for one image's features.
    pub fn image_term(&self, features: &[f32]) -> Vec<f32> {
        let mut out = vec![0.0; self.weights.width];
        self.weights
            .image
            .apply(self.kernels, features, 1, &mut out);
        out
    }

    /// The rotation half of the first layer, `W_R·enc(R) + b_R`, of `encodings` (row-major
    /// `[n, rotation_dim]`): `[n, width]`, tiles spread over the cores.
    pub fn project_rotations(&self, encodings: &[f32]) -> Vec<f32> {
        let e = self.weights.rotation.inputs;
        let n = encodings.len() / e;
        let w = self.weights.width;
        let mut out = vec![0.0; n * w];
        let rows = tile_rows();
        out.par_chunks_mut(rows * w)
            .zip(encodings.par_chunks(rows * e))
            .for_each(|(out, enc)| {
                self.weights
                    .rotation
                    .apply(self.kernels, enc, enc.len() / e, out)
            });
        out
    }

    /// Both branches' log-weights `(s_θ, s_φ)` of the rotations whose projections are
    /// `projected` (`[n, width]`, [`FusedHead::project_rotations`]), for one image's
    /// [`FusedHead::image_term`].
    pub fn branch_scores(&self, image_term: &[f32], projected: &[f32]) -> (Vec<f32>, Vec<f32>) {
        self.projected_scores(image_term, projected, Branches::Both)
    }

    /// [`FusedHead::branch_scores`] of `branches` in f32 (0 for a branch left out).
    fn projected_scores(
        &self,
        image_term: &[f32],
        projected: &[f32],
        branches: Branches,
    ) -> (Vec<f32>, Vec<f32>) {
        if let Some(native) = &self.f32_native {
            return native.branch_scores(image_term, Rows::Projected(projected), branches);
        }
        let (w, rows) = (self.weights.width, tile_rows());
        by_tiles(
            projected,
            w,
            rows,
            branches,
            || Scratch {
                x: vec![0.0; rows * w],
                a: vec![0.0; rows * w],
                b: vec![0.0; rows * w],
            },
            |scratch, projected, out| self.tile(image_term, projected, scratch, out),
        )
    }

    /// Both branches' log-weights `(s_θ, s_φ)` of `rows` in `precision`, for one image's
    /// [`FusedHead::image_term`]. Encoded rows are projected first in f32; in a reduced
    /// precision the projection runs inside the tiles too.
    pub fn branch_scores_in(
        &self,
        precision: Precision,
        image_term: &[f32],
        rows: Rows<'_>,
    ) -> (Vec<f32>, Vec<f32>) {
        self.branch_scores_of(precision, image_term, rows, Branches::Both)
    }

    /// [`FusedHead::branch_scores_in`] of `branches` (0 for a branch left out: the shape branch
    /// alone costs half the arithmetic of both, past the shared first layer).
    pub fn branch_scores_of(
        &self,
        precision: Precision,
        image_term: &[f32],
        rows: Rows<'_>,
        branches: Branches,
    ) -> (Vec<f32>, Vec<f32>) {
        match (self.reduced(precision), rows) {
            (Some(reduced), _) => {
                let scores = reduced.branch_scores_of(image_term, rows, branches);
                if scores.0.iter().chain(&scores.1).all(|s| s.is_finite()) {
                    return scores;
                }
                // f16 tops out at 65 504: a network whose activations pass it scores infinities
                // and NaNs, which rank nothing. Such rows are scored again in f32.
                tracing::warn!(
                    "{precision} scores not finite (out of its range): scored again in f32"
                );
                self.branch_scores_of(Precision::F32, image_term, rows, branches)
            }
            (_, Rows::Projected(projected)) => {
                self.projected_scores(image_term, projected, branches)
            }
            (_, Rows::Encoded(encodings)) if self.rounds_to != Precision::F32 => {
                let round = rounding(self.rounds_to);
                let rounded: Vec<f32> = encodings.iter().copied().map(round).collect();
                self.projected_scores(image_term, &self.project_rotations(&rounded), branches)
            }
            (_, Rows::Encoded(encodings)) => match &self.f32_native {
                Some(native) => native.branch_scores(image_term, rows, branches),
                None => {
                    self.projected_scores(image_term, &self.project_rotations(encodings), branches)
                }
            },
        }
    }

    /// `s_θ + s_φ` of `rows` in `precision` ([`FusedHead::branch_scores_in`] summed).
    pub fn scores_in(&self, precision: Precision, image_term: &[f32], rows: Rows<'_>) -> Vec<f32> {
        self.scores_of(precision, image_term, rows, Branches::Both)
    }

    /// The sum of `branches`' log-weights of `rows` in `precision`: `s_θ + s_φ`, or `s_θ` alone
    /// ([`FusedHead::branch_scores_of`] summed).
    pub fn scores_of(
        &self,
        precision: Precision,
        image_term: &[f32],
        rows: Rows<'_>,
        branches: Branches,
    ) -> Vec<f32> {
        let (mut shape, feature) = self.branch_scores_of(precision, image_term, rows, branches);
        for (s, f) in shape.iter_mut().zip(feature) {
            *s += f;
        }
        shape
    }

    /// One tile: the shared input, then the layers of each branch `out` holds an output for (the
    /// shape branch first), into `out[branch][row]`.
    fn tile(
        &self,
        image_term: &[f32],
        projected: &[f32],
        scratch: &mut Scratch,
        out: &mut [&mut [f32]],
    ) {
        let w = self.weights.width;
        let rows = projected.len() / w;
        let Scratch { x, a, b } = scratch;
        for (xr, pr) in x.chunks_exact_mut(w).zip(projected.chunks_exact(w)) {
            for ((xv, &p), &i) in xr.iter_mut().zip(pr).zip(image_term) {
                *xv = (p + i).max(0.0);
            }
        }
        round_activations(self.rounds_to, &mut x[..rows * w], w);
        for (branch, out) in self.weights.branches.iter().zip(out.iter_mut()) {
            // Ping-pong between the two activation buffers; 0 is the shared input.
            let mut current = 0;
            for (l, layer) in branch.hidden.iter().enumerate() {
                let (input, output) = match current {
                    0 => (&x[..], &mut a[..]),
                    1 => (&a[..], &mut b[..]),
                    _ => (&b[..], &mut a[..]),
                };
                layer.apply(self.kernels, input, rows, output);
                relu(&mut output[..rows * w]);
                // The last hidden layer feeds the f32 dot product, as in the native kernel.
                if l + 1 < branch.hidden.len() {
                    round_activations(self.rounds_to, &mut output[..rows * w], w);
                }
                current = if current == 1 { 2 } else { 1 };
            }
            let last = match current {
                0 => &x[..],
                1 => &a[..],
                _ => &b[..],
            };
            for (o, hr) in out.iter_mut().zip(last.chunks_exact(w)) {
                *o = hr
                    .iter()
                    .zip(&branch.output)
                    .map(|(a, b)| a * b)
                    .sum::<f32>()
                    + branch.output_bias;
            }
        }
    }
}

/// The head in a reduced precision (bfloat16 or f16): the native kernel where the core has it,
/// the emulation elsewhere.
#[derive(Debug, Clone)]
pub struct ReducedHead(Path);

/// The kernel a [`ReducedHead`] runs on.
#[derive(Debug, Clone)]
enum Path {
    /// `TDPBF16PS` on AMX tiles.
    Amx(Box<NativeHead<AmxBf16>>),
    /// The AMX kernel on tiles emulated in software.
    AmxEmulated(Box<NativeHead<EmulatedAmxBf16>>),
    /// `VDPBF16PS` on packed weights.
    Bf16(Box<NativeHead<Bf16Kernel>>),
    /// `VFMADD231PH` on packed weights.
    F16(Box<NativeHead<F16Kernel>>),
    /// `VPDPBUSD` (or `VPMADDWD`) on packed bytes.
    I8(Box<I8Head>),
    /// The f32 GEMM on rounded weights, rounding each GEMM's input.
    Emulated(Box<FusedHead>),
}

impl ReducedHead {
    /// The native kernel of `precision` when `kernels` allows it and this core has its
    /// instructions (and every branch has a hidden layer), else the emulation: bfloat16 on AMX
    /// tiles, else on `VDPBF16PS`; f16 on `VFMADD231PH`; i8 on AMX-INT8 tiles, else on
    /// `VPDPBUSD` (512- or 256-bit), else on AVX2's `VPMADDWD`.
    pub(super) fn new(head: &HeadWeights, precision: Precision, kernels: Kernels) -> ReducedHead {
        let native = match precision {
            // 256-bit AVX-VNNI where the kernels are capped and the core has it, else AVX2.
            Precision::I8 => I8Head::new(head, kernels).map(|n| Path::I8(Box::new(n))),
            _ if !kernels.allows_avx512() => None,
            Precision::Bf16 => kernels
                .allows_amx()
                .then(|| NativeHead::new(head).map(|n| Path::Amx(Box::new(n))))
                .flatten()
                .or_else(|| NativeHead::new(head).map(|n| Path::Bf16(Box::new(n)))),
            Precision::F16 => NativeHead::new(head).map(|n| Path::F16(Box::new(n))),
            Precision::F32 => None,
        };
        ReducedHead(native.unwrap_or_else(|| {
            Path::Emulated(Box::new(FusedHead::rounded_to(head, precision, kernels)))
        }))
    }

    /// The emulation of `precision` (bfloat16 or f16), on any core.
    pub fn emulated(head: &FusedHead, precision: Precision) -> ReducedHead {
        ReducedHead(Path::Emulated(Box::new(FusedHead::rounded_to(
            &head.weights,
            precision,
            head.kernels,
        ))))
    }

    /// The AMX bfloat16 kernel on tiles emulated in software ([`super::amx`]): the kernel's
    /// loop, pointers and epilogue on any core, at a fraction of the f32 rate. For the tests.
    pub fn amx_emulated(head: &FusedHead) -> ReducedHead {
        let native = NativeHead::new(&head.weights).expect("every branch has a hidden layer");
        ReducedHead(Path::AmxEmulated(Box::new(native)))
    }

    /// The 8-bit head's tile kernel (`TDPBUSD`) on tiles emulated in software
    /// ([`super::amx::gemm_i8_tiles`]), on any core. For the tests.
    pub fn amx_int8_emulated(head: &FusedHead) -> ReducedHead {
        let native = I8Head::amx_emulated(&head.weights).expect("every branch has a hidden layer");
        ReducedHead(Path::I8(Box::new(native)))
    }

    /// The 8-bit head on AVX2's `VPMADDWD` kernel (bytes widened to 16-bit pairs), the one
    /// cores with AVX2 and no VNNI run, on any core with AVX2 and FMA (`None` elsewhere). For
    /// the tests.
    pub fn i8_avx2_pairs(head: &FusedHead) -> Option<ReducedHead> {
        I8Head::avx2_pairs(&head.weights).map(|native| ReducedHead(Path::I8(Box::new(native))))
    }

    /// Whether this is a native kernel.
    pub fn is_native(&self) -> bool {
        match &self.0 {
            Path::Emulated(_) | Path::AmxEmulated(_) => false,
            Path::I8(native) => native.is_native(),
            _ => true,
        }
    }

    /// The kernel it runs on, in words.
    pub fn kernel_name(&self) -> &'static str {
        match &self.0 {
            Path::Amx(_) => super::amx::KERNEL_NAME,
            Path::AmxEmulated(_) => "AMX bf16 tiles, emulated",
            Path::Bf16(_) => "AVX-512 BF16 kernel",
            Path::F16(_) => "AVX-512 FP16 kernel",
            Path::I8(native) => native.kernel_name(),
            Path::Emulated(_) => "emulated on the f32 GEMM",
        }
    }

    /// Both branches' log-weights of `rows`, as [`FusedHead::branch_scores_in`]. From encodings,
    /// the native kernels run the rotation half of the first layer in their precision too,
    /// inside the tiles (no projection pass).
    pub fn branch_scores(&self, image_term: &[f32], rows: Rows<'_>) -> (Vec<f32>, Vec<f32>) {
        self.branch_scores_of(image_term, rows, Branches::Both)
    }

    /// The `branches`' log-weights of `rows` (0 for a branch left out).
    pub fn branch_scores_of(
        &self,
        image_term: &[f32],
        rows: Rows<'_>,
        branches: Branches,
    ) -> (Vec<f32>, Vec<f32>) {
        match &self.0 {
            Path::Amx(native) => native.branch_scores(image_term, rows, branches),
            Path::AmxEmulated(native) => native.branch_scores(image_term, rows, branches),
            Path::Bf16(native) => native.branch_scores(image_term, rows, branches),
            Path::F16(native) => native.branch_scores(image_term, rows, branches),
            Path::I8(native) => native.branch_scores(image_term, rows, branches),
            Path::Emulated(head) => {
                head.branch_scores_of(Precision::F32, image_term, rows, branches)
            }
        }
    }
}
