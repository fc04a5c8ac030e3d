//! Which kernels the heads may use: a setting (`--kernels`, `ALIGNIST_KERNELS`) that both the
//! project's own kernels ([`super::native`]) and the library GEMM (`net::dense`) read.

/// The widest kernels a head may use; each falls back to the next narrower one the core has.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub enum Kernels {
    /// The widest the core has: AMX tiles for bfloat16 and 8-bit integers where the core has
    /// AMX-BF16 and AMX-INT8, AVX-512 (f32,
    /// bfloat16 with AVX-512 BF16, f16 with AVX-512 FP16, 8-bit with AVX-512 VNNI), else AVX2;
    /// the library GEMM is the `gemm` crate (512-bit where the core has AVX-512).
    #[default]
    Widest,
    /// As [`Kernels::Widest`] without AMX tiles (bfloat16 on `VDPBF16PS`, 8-bit on `VPDPBUSD`).
    Avx512,
    /// The project's kernels at most 256-bit; bfloat16 and f16 emulated; the library GEMM is
    /// matrixmultiply (which picks its own kernel at run time, 512-bit on AVX-512 cores).
    Avx2,
    /// No kernel of the project's: matrixmultiply's GEMM only; bfloat16 and f16 emulated.
    Portable,
}

impl Kernels {
    /// The environment variable that caps the kernels (`ALIGNIST_KERNELS=avx2`).
    pub const ENV: &'static str = "ALIGNIST_KERNELS";

    /// The name used by flags and the environment (`widest`, `avx512`, `avx2`, `portable`).
    pub fn name(self) -> &'static str {
        match self {
            Kernels::Widest => "widest",
            Kernels::Avx512 => "avx512",
            Kernels::Avx2 => "avx2",
            Kernels::Portable => "portable",
        }
    }

    /// The kernels `ALIGNIST_KERNELS` names ([`Kernels::Widest`] when it is unset, or, with a
    /// warning, when it names none).
    pub fn from_env() -> Kernels {
        match std::env::var(Self::ENV) {
            Ok(name) => name.parse().unwrap_or_else(|e| {
                tracing::warn!("{}: {e}; using the widest kernels", Self::ENV);
                Kernels::Widest
            }),
            Err(_) => Kernels::Widest,
        }
    }

    /// Whether AMX tiles may run.
    pub fn allows_amx(self) -> bool {
        self == Kernels::Widest
    }

    /// Whether the 512-bit kernels may run.
    pub fn allows_avx512(self) -> bool {
        matches!(self, Kernels::Widest | Kernels::Avx512)
    }

    /// Whether the project's own kernels may run.
    pub fn allows_own(self) -> bool {
        self != Kernels::Portable
    }
}

impl std::fmt::Display for Kernels {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(self.name())
    }
}

impl std::str::FromStr for Kernels {
    type Err = String;
    fn from_str(s: &str) -> Result<Self, Self::Err> {
        match s {
            "widest" => Ok(Kernels::Widest),
            "avx512" => Ok(Kernels::Avx512),
            "avx2" => Ok(Kernels::Avx2),
            "portable" => Ok(Kernels::Portable),
            other => Err(format!(
                "unknown kernels `{other}` (widest, avx512, avx2 or portable)"
            )),
        }
    }
}
