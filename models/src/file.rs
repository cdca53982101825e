//! Reading a model file from disk without trusting its size: a path such as `/dev/zero` or a
//! multi-gigabyte file is refused after [`MAX_MODEL_FILE_BYTES`] instead of filling memory.

use std::io::Read;
use std::path::Path;

/// The largest model file any tool reads: 1 MiB. The format's actors are far smaller (the
/// shipped ones are about 50 KB; the onboard weight budget is 64 KiB).
pub const MAX_MODEL_FILE_BYTES: u64 = 1 << 20;

/// Why a model file could not be read.
#[derive(Debug)]
pub enum ReadModelError {
    /// The operating system refused (missing, unreadable).
    Io(std::io::Error),
    /// The file holds more than [`MAX_MODEL_FILE_BYTES`] bytes.
    TooLarge,
}

impl std::fmt::Display for ReadModelError {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            ReadModelError::Io(e) => write!(f, "{e}"),
            ReadModelError::TooLarge => write!(
                f,
                "more than {MAX_MODEL_FILE_BYTES} bytes: not a model file (models are tens of KB)"
            ),
        }
    }
}

impl std::error::Error for ReadModelError {
    fn source(&self) -> Option<&(dyn std::error::Error + 'static)> {
        match self {
            ReadModelError::Io(e) => Some(e),
            ReadModelError::TooLarge => None,
        }
    }
}

/// The bytes of the model file at `path`, at most [`MAX_MODEL_FILE_BYTES`] of them.
///
/// ```
/// # #[cfg(unix)] {
/// let err = skyherd_model::read_model_file(std::path::Path::new("/dev/zero")).unwrap_err();
/// assert!(err.to_string().contains("not a model file"));
/// # }
/// ```
pub fn read_model_file(path: &Path) -> Result<Vec<u8>, ReadModelError> {
    let file = std::fs::File::open(path).map_err(ReadModelError::Io)?;
    let mut bytes = Vec::new();
    file.take(MAX_MODEL_FILE_BYTES + 1)
        .read_to_end(&mut bytes)
        .map_err(ReadModelError::Io)?;
    if bytes.len() as u64 > MAX_MODEL_FILE_BYTES {
        return Err(ReadModelError::TooLarge);
    }
    Ok(bytes)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_file_past_the_cap_is_refused_and_one_below_is_read() {
        let dir = std::env::temp_dir().join(format!("skyherd-model-file-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let big = dir.join("big.skym");
        std::fs::write(&big, vec![0u8; MAX_MODEL_FILE_BYTES as usize + 1]).unwrap();
        assert!(matches!(
            read_model_file(&big),
            Err(ReadModelError::TooLarge)
        ));
        let small = dir.join("small.skym");
        std::fs::write(&small, b"SKYM").unwrap();
        assert_eq!(read_model_file(&small).unwrap(), b"SKYM");
        let missing = read_model_file(&dir.join("missing.skym")).unwrap_err();
        assert!(matches!(missing, ReadModelError::Io(_)));
        let _ = std::fs::remove_dir_all(&dir);
    }
}
