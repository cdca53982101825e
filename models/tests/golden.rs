//! Pins the model file bytes: the seeded model in `golden/` must be exactly what the encoder and
//! quantizer produce today. Regenerate deliberately with `SKYHERD_BLESS=1 cargo test`.
#![cfg(feature = "std")]

use std::path::PathBuf;

use skyherd_model::{ActorShape, FloatActor, ModelMeta, SplitMix64, Task, decode, quantize};

/// The golden model's shape: the onboard encoder's 46 features (encoder v3), 32 hidden units,
/// two shared layers. Its weights are seeded random numbers, not trained.
pub const GOLDEN_SHAPE: ActorShape = ActorShape {
    features: 46,
    hidden: 32,
    shared_layers: 2,
};
const GOLDEN_FILE: &str = "golden/seeded-f46-h32-s2.skym";

fn golden_model() -> Vec<u8> {
    let actor = FloatActor::random(GOLDEN_SHAPE, 2026);
    let mut rng = SplitMix64::new(4);
    let calibration: Vec<(Task, Vec<f32>)> = (0..256)
        .map(|i| {
            let features = (0..GOLDEN_SHAPE.features)
                .map(|_| rng.uniform(-3.0, 3.0) as f32)
                .collect();
            (Task::ALL[i % 2], features)
        })
        .collect();
    let meta = ModelMeta {
        encoder_version: 3,
        max_speed: 5.0,
    };
    quantize(&actor, meta, calibration.iter().map(|(t, f)| (*t, &f[..]))).unwrap()
}

fn path(relative: &str) -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR")).join(relative)
}

#[test]
fn seeded_model_bytes_are_pinned() {
    let bytes = golden_model();
    let file = path(GOLDEN_FILE);
    if std::env::var_os("SKYHERD_BLESS").is_some() {
        std::fs::write(&file, &bytes).unwrap();
    }
    let stored = std::fs::read(&file).expect("golden model missing; run with SKYHERD_BLESS=1");
    assert!(
        stored == bytes,
        "model encoder or quantizer output drifted from {GOLDEN_FILE}; if intended, bless it"
    );
    // The header layout itself, byte by byte (format version 2).
    #[rustfmt::skip]
    let header: [u8; 32] = [
        b'S', b'K', b'Y', b'M', 2, 0, 32, 0,   // magic, format version, header length
        0, 0, 0, 0,                            // file length (checked below)
        3, 0, 46, 0, 32, 0,                    // encoder v3, 46 features, hidden 32
        2, 2, 3, 0, 0, 0,                      // 2 tasks, 2 shared layers, 3 actions, reserved
        0x00, 0x00, 0xa0, 0x40,                // max speed 5.0 m/s
        0, 0, 0, 0,                            // reserved
    ];
    assert_eq!(&stored[..8], &header[..8]);
    assert_eq!(
        u32::from_le_bytes(stored[8..12].try_into().unwrap()) as usize,
        stored.len()
    );
    assert_eq!(&stored[12..32], &header[12..32]);
    let model = decode(&stored).unwrap();
    assert_eq!(model.file_len(), skyherd_model::format::file_len(46, 32, 2));
}
