//! Linear layers as plain row-major matrices, and the one strided library GEMM every hand-written
//! path without a kernel of its own calls (the inference head's image term and rotation
//! projections, the portable inference tiles, the training head and encoder): the `gemm` crate,
//! on 512-bit FMAs where the core has AVX-512, or matrixmultiply (which picks its own kernel at
//! run time) when the kernels are capped (`--kernels`/`ALIGNIST_KERNELS` `avx2` or `portable`,
//! [`Kernels`]).

use burn::tensor::Tensor;

use super::kernels::Kernels;

/// One linear layer, row-major `[inputs, outputs]` weights (burn's `Linear` layout: `y = x·W + b`).
#[derive(Debug, Clone)]
pub(crate) struct Dense {
    pub(crate) inputs: usize,
    pub(crate) outputs: usize,
    pub(crate) weight: Vec<f32>,
    pub(crate) bias: Vec<f32>,
}

impl Dense {
    /// Reads a burn layer's weights (and its bias, zero when it has none).
    pub(crate) fn of(linear: &burn::nn::Linear) -> Dense {
        let weight = linear.weight.val();
        let [inputs, outputs] = weight.dims();
        Dense {
            inputs,
            outputs,
            weight: read(weight),
            bias: linear
                .bias
                .as_ref()
                .map_or_else(|| vec![0.0; outputs], |b| read(b.val())),
        }
    }

    /// `out[r] = x[r]·W + b` for the `rows` rows of `x` (row-major), single-threaded, on the
    /// library GEMM `kernels` allows.
    pub(crate) fn apply(&self, kernels: Kernels, x: &[f32], rows: usize, out: &mut [f32]) {
        for row in out[..rows * self.outputs].chunks_exact_mut(self.outputs) {
            row.copy_from_slice(&self.bias);
        }
        gemm(
            kernels,
            [rows, self.inputs, self.outputs],
            Strided::rows(x, self.inputs),
            Strided::rows(&self.weight, self.outputs),
            1.0,
            out,
        );
    }

    /// `W` read as its transpose `[outputs, inputs]` (no copy): the backward pass's `dY·Wᵀ`.
    pub(crate) fn transposed(&self) -> Strided<'_> {
        Strided::columns(&self.weight, self.outputs)
    }
}

/// The values of a float tensor, in order.
pub(crate) fn read<const D: usize>(t: Tensor<D>) -> Vec<f32> {
    t.into_data()
        .convert::<f32>()
        .try_to_vec::<f32>()
        .expect("float weights")
}

/// A matrix operand: its elements and the steps between rows and between columns.
#[derive(Debug, Clone, Copy)]
pub(crate) struct Strided<'a> {
    data: &'a [f32],
    row_step: usize,
    column_step: usize,
}

impl<'a> Strided<'a> {
    /// A row-major matrix with `columns` columns.
    pub(crate) fn rows(data: &'a [f32], columns: usize) -> Self {
        Strided {
            data,
            row_step: columns,
            column_step: 1,
        }
    }

    /// The transpose of a row-major matrix with `columns` columns (its rows read as columns).
    pub(crate) fn columns(data: &'a [f32], columns: usize) -> Self {
        Strided {
            data,
            row_step: 1,
            column_step: columns,
        }
    }

    /// Whether an `[m, n]` matrix with these steps lies inside the data.
    fn holds(&self, m: usize, n: usize) -> bool {
        m == 0 || n == 0 || (m - 1) * self.row_step + (n - 1) * self.column_step < self.data.len()
    }
}

/// The library [`gemm`] runs on for `kernels`.
pub(crate) fn library_name(kernels: Kernels) -> &'static str {
    match kernels.allows_avx512() {
        true => "the gemm crate",
        false => "matrixmultiply",
    }
}

/// `c = beta·c + a·b` for `[m, k]·[k, n]` operands, `c` row-major `[m, n]`, on the calling
/// thread: the `gemm` crate (its widest kernel on this core) unless `kernels` are capped below
/// AVX-512, then matrixmultiply's (256-bit at most).
///
/// # Panics
/// When an operand is smaller than its shape: a caller's bug, never input-dependent.
pub(crate) fn gemm(
    kernels: Kernels,
    [m, k, n]: [usize; 3],
    a: Strided<'_>,
    b: Strided<'_>,
    beta: f32,
    c: &mut [f32],
) {
    assert!(
        a.holds(m, k) && b.holds(k, n) && c.len() >= m * n,
        "gemm operands smaller than [{m}, {k}]·[{k}, {n}]"
    );
    if m == 0 || n == 0 {
        return;
    }
    if kernels.allows_avx512() {
        // SAFETY: the assertion above keeps every index the GEMM reads (`i·row_step +
        // j·column_step` for `i < rows`, `j < columns`) inside `a` and `b`, and every index it
        // writes inside `c`; `c` is a unique borrow, so it aliases neither operand. With
        // `read_dst` false `c` is only written (`dst := beta·dst + 1·a·b` otherwise).
        unsafe {
            gemm::gemm(
                m,
                n,
                k,
                c.as_mut_ptr(),
                1,
                n as isize,
                beta != 0.0,
                a.data.as_ptr(),
                a.column_step as isize,
                a.row_step as isize,
                b.data.as_ptr(),
                b.column_step as isize,
                b.row_step as isize,
                beta,
                1.0,
                false,
                false,
                false,
                gemm::Parallelism::None,
            );
        }
        return;
    }
    // SAFETY: as above.
    unsafe {
        matrixmultiply::sgemm(
            m,
            k,
            n,
            1.0,
            a.data.as_ptr(),
            a.row_step as isize,
            a.column_step as isize,
            b.data.as_ptr(),
            b.row_step as isize,
            b.column_step as isize,
            beta,
            c.as_mut_ptr(),
            n as isize,
            1,
        );
    }
}
