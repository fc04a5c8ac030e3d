//! The one place where the compute device is chosen (DESIGN.md §4: keep the backend one switch).
//!
//! The default is burn's ndarray backend (measured 2× faster than flex for the head's matmuls on
//! the 2-core CPU); building with `--features flex` switches every part of the project to flex.

use burn::tensor::Device;

/// The device every network, expert and encoding of the project runs on.
pub fn device() -> Device {
    #[cfg(feature = "flex")]
    {
        Device::flex()
    }
    #[cfg(not(feature = "flex"))]
    {
        // burn 0.22 marks ndarray deprecated in favour of flex; it is still the faster choice
        // for our matmul-bound workloads (DESIGN.md §4).
        #[allow(deprecated)]
        Device::ndarray()
    }
}

/// Name of the backend compiled in, for logs and reports.
pub fn backend_name() -> &'static str {
    if cfg!(feature = "flex") {
        "flex"
    } else {
        "ndarray"
    }
}
