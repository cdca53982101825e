//! MAVLink 2 message signing: keys, key files and the one signing set-up every link uses.
//!
//! <https://mavlink.io/en/guide/message_signing.html>: a 48-bit timestamp in 10 us units
//! since 2015-01-01 per (system, component, link id) stream, a SHA-256 based signature under
//! a 32-byte secret key. The `mavlink` crate keeps the timestamps; [`signing_config`] is the
//! only place its options are chosen.

use std::path::Path;

use thiserror::Error;

/// Length of a MAVLink 2 signing key, bytes.
pub const KEY_LEN: usize = 32;

/// A 32-byte MAVLink 2 signing key.
#[derive(Clone, PartialEq, Eq)]
pub struct SigningKey(pub [u8; KEY_LEN]);

impl std::fmt::Debug for SigningKey {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        // Never print key material.
        f.write_str("SigningKey(..)")
    }
}

/// Why a signing key file could not be used.
#[derive(Debug, Error)]
pub enum KeyFileError {
    /// The file could not be read.
    #[error("cannot read signing key file {path}: {source}")]
    Io {
        /// The file.
        path: String,
        /// The I/O error.
        source: std::io::Error,
    },
    /// Group or others may read or write the file: the key may already be known.
    #[error(
        "signing key file {path} has mode {mode:o}: group and others must have no access (chmod 600 it, or make a new key with skyherd-ground keygen)"
    )]
    TooOpen {
        /// The file.
        path: String,
        /// Its permission bits.
        mode: u32,
    },
    /// The file could not be created (it exists already, or its folder is missing).
    #[error("cannot create signing key file {path}: {source}")]
    Create {
        /// The file.
        path: String,
        /// The I/O error.
        source: std::io::Error,
    },
    /// The operating system gave no randomness.
    #[error("no randomness from the operating system for a key: {0}")]
    NoRandomness(String),
    /// The file is neither 32 raw bytes nor 64 hex digits.
    #[error("signing key file {path} must hold 32 raw bytes or 64 hex digits, found {len} bytes")]
    BadLength {
        /// The file.
        path: String,
        /// Its length in bytes (after trimming whitespace for the hex form).
        len: usize,
    },
}

/// A key file is at most this long (64 hex digits and whitespace); more is not read.
const MAX_KEY_FILE_BYTES: u64 = 4096;

impl SigningKey {
    /// A key from a key file's bytes: exactly 32 raw bytes, or 64 hex digits (whitespace
    /// around ignored); `None` for anything else.
    ///
    /// ```
    /// use skyherd_link::SigningKey;
    /// assert_eq!(SigningKey::parse(&[7u8; 32]), Some(SigningKey([7; 32])));
    /// assert_eq!(SigningKey::parse("ab".repeat(32).as_bytes()), Some(SigningKey([0xab; 32])));
    /// assert_eq!(SigningKey::parse(b"too short"), None);
    /// ```
    pub fn parse(bytes: &[u8]) -> Option<Self> {
        if let Ok(key) = <[u8; KEY_LEN]>::try_from(bytes) {
            return Some(Self(key));
        }
        let hex = bytes.trim_ascii();
        if hex.len() != 2 * KEY_LEN {
            return None;
        }
        let nibble = |c: u8| char::from(c).to_digit(16);
        let mut key = [0u8; KEY_LEN];
        for (k, pair) in key.iter_mut().zip(hex.chunks_exact(2)) {
            // Two hex digits: at most 255.
            *k = (nibble(pair[0])? * 16 + nibble(pair[1])?) as u8;
        }
        Some(Self(key))
    }

    /// A fresh key from the operating system's randomness.
    ///
    /// # Errors
    /// [`KeyFileError::NoRandomness`] when the operating system has none to give.
    pub fn generate() -> Result<Self, KeyFileError> {
        let mut key = [0u8; KEY_LEN];
        getrandom::fill(&mut key).map_err(|e| KeyFileError::NoRandomness(e.to_string()))?;
        Ok(Self(key))
    }

    /// Writes the key to a new file, as 64 hex digits and a newline: created with
    /// `O_CREAT | O_EXCL` (an existing file or a symlink in its place is an error, never
    /// followed or overwritten) and, on Unix, mode 0600 from the start.
    ///
    /// # Errors
    /// [`KeyFileError::Create`] when the file exists or cannot be written.
    pub fn write_new_file(&self, path: &Path) -> Result<(), KeyFileError> {
        use std::io::Write;
        let mut options = std::fs::OpenOptions::new();
        options.write(true).create_new(true);
        #[cfg(unix)]
        {
            use std::os::unix::fs::OpenOptionsExt;
            options.mode(0o600);
        }
        let hex: String = self.0.iter().map(|b| format!("{b:02x}")).collect();
        options
            .open(path)
            .and_then(|mut f| {
                f.write_all(format!("{hex}\n").as_bytes())?;
                f.sync_all()
            })
            .map_err(|source| KeyFileError::Create {
                path: path.display().to_string(),
                source,
            })
    }

    /// Read a key file: exactly 32 raw bytes, or 64 hex digits (whitespace around ignored).
    /// On Unix the file must not be open to group or others (as ssh insists for its keys),
    /// and at most 4 KiB of it is read, so `/dev/zero` is refused rather than read forever.
    ///
    /// # Errors
    /// [`KeyFileError`] when the file is unreadable, too open or has the wrong length.
    pub fn from_file(path: &Path) -> Result<Self, KeyFileError> {
        use std::io::Read;
        let name = path.display().to_string();
        let io = |source| KeyFileError::Io {
            path: name.clone(),
            source,
        };
        let file = std::fs::File::open(path).map_err(io)?;
        #[cfg(unix)]
        {
            use std::os::unix::fs::PermissionsExt;
            let meta = file.metadata().map_err(io)?;
            let mode = meta.permissions().mode();
            if meta.is_file() && mode & 0o077 != 0 {
                return Err(KeyFileError::TooOpen {
                    path: name,
                    mode: mode & 0o777,
                });
            }
        }
        let mut bytes = Vec::new();
        file.take(MAX_KEY_FILE_BYTES + 1)
            .read_to_end(&mut bytes)
            .map_err(io)?;
        if bytes.len() as u64 > MAX_KEY_FILE_BYTES {
            return Err(KeyFileError::BadLength {
                path: name,
                len: bytes.len(),
            });
        }
        if let Some(key) = Self::parse(&bytes) {
            return Ok(key);
        }
        Err(KeyFileError::BadLength {
            path: name,
            len: bytes.trim_ascii().len(),
        })
    }
}

/// Signing policy of one link.
#[derive(Debug, Clone)]
pub struct Signing {
    /// The shared secret.
    pub key: SigningKey,
    /// Link id written into outgoing signatures (distinguishes links sharing a key).
    pub link_id: u8,
    /// Accept unsigned incoming frames (for migration only; off on the drone links).
    pub accept_unsigned: bool,
}

/// The `mavlink` crate's signing options for `key` on outgoing `link_id`: sign every frame,
/// and (for `MavConnection` users) refuse unsigned incoming frames. Every signed link in
/// skyherd is set up here.
pub fn signing_config(key: &SigningKey, link_id: u8) -> mavlink::SigningConfig {
    mavlink::SigningConfig::new(key.0, link_id, true, false)
}

/// The signing state (keys, per-stream timestamps) for [`signing_config`].
pub fn signing_data(key: &SigningKey, link_id: u8) -> mavlink::SigningData {
    mavlink::SigningData::from_config(signing_config(key, link_id))
}
