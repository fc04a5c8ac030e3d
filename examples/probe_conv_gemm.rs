//! The `gemm` crate on the convolution GEMMs of the training encoder (`tiny_deep`, 48 px crops):
//! one image, one thread, GFLOP/s of the forward `Y = W·cols`, of the weight gradient
//! `dW = dY·colsᵀ` read from im2col's columns (`[taps, pixels]`, the layout before
//! `encoder_grad::im2row`) and from im2row's rows (`[pixels, taps]`, the layout it runs on now),
//! and of the input gradient's `Wᵀ·dY`. A profile of the encoder's GEMMs alone, against the
//! core's FMA peak (`alignist-train bench` prints it).
//! `cargo run --release --example probe_conv_gemm`
use std::time::Instant;

/// `c = [beta·c +] a·b` for `[m, k]·[k, n]`, `c` row-major, operands by (row step, column step).
fn product(
    [m, k, n]: [usize; 3],
    (a, a_rs, a_cs): (&[f32], usize, usize),
    (b, b_rs, b_cs): (&[f32], usize, usize),
    c: &mut [f32],
    accumulate: bool,
) {
    assert!(a.len() >= m * k && b.len() >= k * n && c.len() >= m * n);
    // SAFETY: every operand holds its shape at these steps (asserted above).
    unsafe {
        gemm::gemm(
            m,
            n,
            k,
            c.as_mut_ptr(),
            1,
            n as isize,
            accumulate,
            a.as_ptr(),
            a_cs as isize,
            a_rs as isize,
            b.as_ptr(),
            b_cs as isize,
            b_rs as isize,
            1.0,
            1.0,
            false,
            false,
            false,
            gemm::Parallelism::None,
        );
    }
}

/// Median seconds of 30 calls after 5 warm-up calls.
fn time(f: &mut dyn FnMut()) -> f64 {
    for _ in 0..5 {
        f();
    }
    let mut v: Vec<f64> = (0..30)
        .map(|_| {
            let t = Instant::now();
            f();
            t.elapsed().as_secs_f64()
        })
        .collect();
    v.sort_by(f64::total_cmp);
    v[15]
}

fn main() {
    // (output channels, taps = c_in·k², output pixels, convolutions of this shape).
    let shapes = [
        (16, 27, 2304, 1),
        (16, 144, 2304, 4),
        (32, 144, 576, 1),
        (32, 16, 576, 1),
        (32, 288, 576, 3),
        (64, 288, 144, 1),
        (64, 32, 144, 1),
        (64, 576, 144, 3),
        (128, 576, 36, 1),
        (128, 64, 36, 1),
        (128, 1152, 36, 3),
    ];
    let mut totals = [0.0; 4];
    for (c_out, taps, pixels, count) in shapes {
        let w = vec![0.5f32; c_out * taps];
        let cols = vec![0.25f32; taps * pixels];
        let dy = vec![0.1f32; c_out * pixels];
        let (mut y, mut dw, mut d_cols) = (
            vec![0.0; c_out * pixels],
            vec![0.0; c_out * taps],
            vec![0.0; taps * pixels],
        );
        let shape = |a, b, c| [a, b, c];
        let times = [
            time(&mut || {
                let s = shape(c_out, taps, pixels);
                product(s, (&w, taps, 1), (&cols, pixels, 1), &mut y, false)
            }),
            time(&mut || {
                let s = shape(c_out, pixels, taps);
                product(s, (&dy, pixels, 1), (&cols, 1, pixels), &mut dw, true)
            }),
            time(&mut || {
                let s = shape(c_out, pixels, taps);
                product(s, (&dy, pixels, 1), (&cols, taps, 1), &mut dw, true)
            }),
            time(&mut || {
                let s = shape(taps, c_out, pixels);
                product(s, (&w, 1, taps), (&dy, pixels, 1), &mut d_cols, false)
            }),
        ];
        let gflops = |t: f64| 2.0 * (c_out * taps * pixels) as f64 / t / 1e9;
        println!(
            "c_out {c_out:>3}, taps {taps:>4}, pixels {pixels:>4} (×{count}): forward {:5.1} | dW from columns {:5.1} | dW from rows {:5.1} | dX {:5.1} GFLOP/s",
            gflops(times[0]),
            gflops(times[1]),
            gflops(times[2]),
            gflops(times[3]),
        );
        for (t, v) in totals.iter_mut().zip(times) {
            *t += v * count as f64;
        }
    }
    println!(
        "one image, ms: forward {:.2}, dW from columns {:.2}, dW from rows {:.2}, dX {:.2}",
        totals[0] * 1e3,
        totals[1] * 1e3,
        totals[2] * 1e3,
        totals[3] * 1e3
    );
}
