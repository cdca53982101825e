//! End-to-end tests across the skyherd crates live in `tests/`; this library holds what they
//! share: where the repository and the workspace's binaries are.

use std::path::{Path, PathBuf};

/// The repository's root.
pub fn repo() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR"))
        .parent()
        .expect("tests/ sits in the repo")
        .to_path_buf()
}

/// The workspace binary `name`, from the same target folder as the running test (`cargo test
/// --workspace` builds them).
///
/// # Panics
/// When it is not there: the test cannot run without it.
pub fn binary(name: &str) -> PathBuf {
    let exe = std::env::current_exe().expect("test executable");
    // target/<profile>/deps/<test> -> target/<profile>/<name>
    let dir = exe
        .parent()
        .and_then(Path::parent)
        .expect("target/<profile>");
    let path = dir.join(name);
    assert!(
        path.exists(),
        "{} is missing: build the workspace binaries (cargo test --workspace does)",
        path.display()
    );
    path
}
