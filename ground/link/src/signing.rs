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
    /// The file is neither 32 raw bytes nor 64 hex digits.
    #[error("signing key file {path} must hold 32 raw bytes or 64 hex digits, found {len} bytes")]
    BadLength {
        /// The file.
        path: String,
        /// Its length in bytes (after trimming whitespace for the hex form).
        len: usize,
    },
}

impl SigningKey {
    /// Read a key file: exactly 32 raw bytes, or 64 hex digits (whitespace around ignored).
    ///
    /// # Errors
    /// [`KeyFileError`] when the file is unreadable or has the wrong length.
    pub fn from_file(path: &Path) -> Result<Self, KeyFileError> {
        let name = path.display().to_string();
        let bytes = std::fs::read(path).map_err(|source| KeyFileError::Io {
            path: name.clone(),
            source,
        })?;
        if let Ok(key) = <[u8; 32]>::try_from(bytes.as_slice()) {
            return Ok(Self(key));
        }
        let text = String::from_utf8_lossy(&bytes);
        let hex = text.trim();
        if hex.len() == 64 && hex.bytes().all(|b| b.is_ascii_hexdigit()) {
            let mut key = [0u8; 32];
            for (i, k) in key.iter_mut().enumerate() {
                *k = u8::from_str_radix(&hex[2 * i..2 * i + 2], 16).unwrap_or(0);
            }
            return Ok(Self(key));
        }
        Err(KeyFileError::BadLength {
            path: name,
            len: hex.len(),
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
