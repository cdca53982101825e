//! The `skyherd-model` CLI on the golden model and on a corrupted copy.
#![cfg(feature = "std")]

use std::process::Command;

const BIN: &str = env!("CARGO_BIN_EXE_skyherd-model");
const GOLDEN: &str = concat!(env!("CARGO_MANIFEST_DIR"), "/golden/seeded-f46-h32-s2.skym");

#[test]
fn inspect_and_validate() {
    let out = Command::new(BIN)
        .args(["inspect", GOLDEN])
        .output()
        .unwrap();
    assert!(out.status.success());
    let text = String::from_utf8(out.stdout).unwrap();
    assert!(
        text.contains("encoder: v3, 46 features; hidden 32 x 2 shared layers"),
        "{text}"
    );
    assert!(text.contains("output[Collecting]"), "{text}");

    let out = Command::new(BIN)
        .args(["validate", GOLDEN])
        .output()
        .unwrap();
    assert!(out.status.success());

    let mut bytes = std::fs::read(GOLDEN).unwrap();
    bytes[100] ^= 1;
    let corrupt = std::env::temp_dir().join(format!("skyherd-corrupt-{}.skym", std::process::id()));
    std::fs::write(&corrupt, &bytes).unwrap();
    let out = Command::new(BIN)
        .arg("validate")
        .arg(&corrupt)
        .output()
        .unwrap();
    std::fs::remove_file(&corrupt).unwrap();
    assert_eq!(out.status.code(), Some(1));
    assert!(
        String::from_utf8(out.stderr)
            .unwrap()
            .contains("CRC mismatch")
    );

    let out = Command::new(BIN).arg("frobnicate").output().unwrap();
    assert_eq!(out.status.code(), Some(2));
}
