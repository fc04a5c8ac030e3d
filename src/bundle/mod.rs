//! Model files: manifests, checksums, weights in safetensors (readable from numpy too), and
//! validation that names the file and the field that is wrong.

pub mod experts;
pub mod model;
pub mod record;
pub mod study;

use std::fs;
use std::io::Write;
use std::path::{Path, PathBuf};

use burn::module::Module;
use burn::store::{ModuleSnapshot, SafetensorsStore};
use serde::{Deserialize, Serialize};

pub use record::FileEntry;
use sha2::{Digest, Sha256};

/// Errors reading or writing model files; each names the file (and the field where one is
/// wrong).
#[derive(Debug, thiserror::Error)]
pub enum BundleError {
    /// A file could not be read or written.
    #[error("{path}: {source}")]
    Io {
        /// The file.
        path: String,
        /// The I/O error.
        source: std::io::Error,
    },
    /// A manifest that is not the JSON it should be (the error names the line, column and
    /// field).
    #[error("{path}: {source}")]
    Json {
        /// The manifest.
        path: String,
        /// The parser's error.
        #[source]
        source: serde_json::Error,
    },
    /// A manifest whose values are wrong (a version, a field out of range).
    #[error("{path}: {message}")]
    Manifest {
        /// The manifest.
        path: String,
        /// What is wrong, naming the field.
        message: String,
    },
    /// A file whose checksum differs from the manifest's.
    #[error(
        "{path}: sha256 is {actual} but the manifest records {expected} (file changed or corrupt)"
    )]
    Checksum {
        /// The file.
        path: String,
        /// Recorded.
        expected: String,
        /// Computed.
        actual: String,
    },
    /// Weights that do not fit the network the manifest describes.
    #[error("{path}: {message}")]
    Weights {
        /// The weight file.
        path: String,
        /// Which tensors are missing, extra or of the wrong shape.
        message: String,
    },
    /// A mesh problem.
    #[error(transparent)]
    Cad(#[from] crate::cad::CadError),
}

/// sha256 of a file, lower-case hex.
pub fn sha256_file(path: &Path) -> Result<FileEntry, BundleError> {
    let bytes = fs::read(path).map_err(|e| io_err(path, e))?;
    Ok(FileEntry {
        sha256: hex::encode(Sha256::digest(&bytes)),
        bytes: bytes.len() as u64,
    })
}

pub(crate) fn io_err(path: &Path, source: std::io::Error) -> BundleError {
    BundleError::Io {
        path: path.display().to_string(),
        source,
    }
}

/// `dir/rel`, refused unless `rel` is a plain relative path that stays inside `dir` (no root, no
/// `..`, and, where it exists, no link that leads out). The error names what is wrong, never the
/// server's own paths.
pub fn inside(dir: &Path, rel: &str) -> Result<PathBuf, String> {
    use std::path::Component;
    let relative = Path::new(rel);
    let plain = !rel.is_empty()
        && relative
            .components()
            .all(|c| matches!(c, Component::Normal(_) | Component::CurDir));
    if !plain {
        return Err(format!(
            "{rel:?} is outside the bundle (not a plain relative path)"
        ));
    }
    let path = dir.join(relative);
    if let (Ok(real), Ok(root)) = (path.canonicalize(), dir.canonicalize())
        && !real.starts_with(&root)
    {
        return Err(format!("{rel:?} leads outside the bundle"));
    }
    Ok(path)
}

/// Checks a file against its manifest entry.
pub fn verify_file(path: &Path, expected: &FileEntry) -> Result<(), BundleError> {
    let actual = sha256_file(path)?;
    if actual.sha256 != expected.sha256 {
        return Err(BundleError::Checksum {
            path: path.display().to_string(),
            expected: expected.sha256.clone(),
            actual: actual.sha256,
        });
    }
    Ok(())
}

/// Writes `bytes` to `path` atomically: a temporary file in the same folder, fsync, rename.
pub fn write_atomic(path: &Path, bytes: &[u8]) -> Result<(), BundleError> {
    let tmp = path.with_extension("partial");
    let mut f = fs::File::create(&tmp).map_err(|e| io_err(&tmp, e))?;
    f.write_all(bytes).map_err(|e| io_err(&tmp, e))?;
    f.sync_all().map_err(|e| io_err(&tmp, e))?;
    fs::rename(&tmp, path).map_err(|e| io_err(path, e))
}

/// Saves a module's weights as safetensors (atomically) and returns the file's entry.
pub fn save_weights<M: Module>(module: &M, path: &Path) -> Result<FileEntry, BundleError> {
    let tmp = path.with_extension("safetensors.partial");
    let mut store = SafetensorsStore::from_file(&tmp).overwrite(true);
    module
        .save_into(&mut store)
        .map_err(|e| BundleError::Weights {
            path: path.display().to_string(),
            message: e.to_string(),
        })?;
    fs::File::open(&tmp)
        .and_then(|f| f.sync_all())
        .map_err(|e| io_err(&tmp, e))?;
    fs::rename(&tmp, path).map_err(|e| io_err(path, e))?;
    sha256_file(path)
}

/// Loads safetensors weights into `module` (built from the manifest's configuration), after
/// checking the file's checksum. Every tensor must be present with the right shape; a file that
/// does not fit is refused with a short account (how many tensors differ, the first few by name
/// with both shapes), not the loader's dump of every one.
pub fn load_weights<M: Module>(
    mut module: M,
    path: &Path,
    expected: &FileEntry,
) -> Result<M, BundleError> {
    verify_file(path, expected)?;
    let mut store = SafetensorsStore::from_file(path)
        .validate(false)
        .allow_partial(true);
    let result = module
        .load_from(&mut store)
        .map_err(|e| BundleError::Weights {
            path: path.display().to_string(),
            message: e.to_string(),
        })?;
    let mut problems = Vec::new();
    if !result.errors.is_empty() {
        let each = result.errors.iter().map(|e| match e {
            burn::store::ApplyError::ShapeMismatch {
                path,
                expected,
                found,
            } => format!(
                "{path} is {:?} in the file, {:?} in the manifest's network",
                found.as_slice(),
                expected.as_slice()
            ),
            other => other.to_string(),
        });
        problems.push(format!(
            "{} tensor(s) do not fit the manifest's `network` (its layout, hidden width, layers or \
             pooling grid?): {}",
            result.errors.len(),
            first_few(each)
        ));
    }
    if !result.missing.is_empty() {
        let names = result.missing.iter().map(|(n, _)| n.clone());
        problems.push(format!(
            "{} tensor(s) missing: {}",
            result.missing.len(),
            first_few(names)
        ));
    }
    if !result.unused.is_empty() {
        problems.push(format!(
            "{} unexpected tensor(s): {}",
            result.unused.len(),
            first_few(result.unused.iter().cloned())
        ));
    }
    if !problems.is_empty() {
        return Err(BundleError::Weights {
            path: path.display().to_string(),
            message: problems.join("; "),
        });
    }
    Ok(module)
}

/// The first three items, then how many more.
fn first_few(items: impl Iterator<Item = String>) -> String {
    let items: Vec<String> = items.collect();
    let shown = items.iter().take(3).cloned().collect::<Vec<_>>().join(", ");
    match items.len().saturating_sub(3) {
        0 => shown,
        more => format!("{shown} and {more} more"),
    }
}

/// Reads and parses a JSON manifest; a parse error names the file, line and field.
pub fn read_manifest<T: for<'de> Deserialize<'de>>(path: &Path) -> Result<T, BundleError> {
    let text = fs::read_to_string(path).map_err(|e| io_err(path, e))?;
    serde_json::from_str(&text).map_err(|source| BundleError::Json {
        path: path.display().to_string(),
        source,
    })
}

/// Reads a manifest and refuses it unless `version_of(manifest)` is `expected`, naming the file.
pub fn read_versioned_manifest<T: for<'de> Deserialize<'de>>(
    path: &Path,
    expected: u32,
    version_of: impl Fn(&T) -> u32,
) -> Result<T, BundleError> {
    let manifest: T = read_manifest(path)?;
    let found = version_of(&manifest);
    if found != expected {
        return Err(BundleError::Manifest {
            path: path.display().to_string(),
            message: format!("format_version is {found} but this build reads {expected}"),
        });
    }
    Ok(manifest)
}

/// Writes a JSON manifest atomically.
pub fn write_manifest<T: Serialize>(path: &Path, manifest: &T) -> Result<(), BundleError> {
    let text = serde_json::to_string_pretty(manifest).map_err(|source| BundleError::Json {
        path: path.display().to_string(),
        source,
    })?;
    write_atomic(path, text.as_bytes())
}
