//! Puts `memory.x` on the linker path and writes the embedded model: seeded, untrained
//! weights in the size of the newest shipped actor (51 features, encoder v4, hidden 128, 2 shared
//! layers), so
//! the flash numbers are the real ones. A trained model file would replace it one for one.

use std::path::PathBuf;

use skyherd_model::{ActorShape, FloatActor, ModelMeta, SplitMix64, Task, quantize};

fn main() {
    let out = PathBuf::from(std::env::var("OUT_DIR").unwrap());
    std::fs::copy("memory.x", out.join("memory.x")).unwrap();
    println!("cargo:rustc-link-search={}", out.display());
    println!("cargo:rerun-if-changed=memory.x");
    println!("cargo:rerun-if-changed=build.rs");

    let hidden: usize = std::env::var("SKYHERD_FIRMWARE_HIDDEN")
        .ok()
        .and_then(|h| h.parse().ok())
        .unwrap_or(128);
    println!("cargo:rerun-if-env-changed=SKYHERD_FIRMWARE_HIDDEN");
    let shape = ActorShape { features: 51, hidden, shared_layers: 2 };
    let mut rng = SplitMix64::new(7);
    let calibration: Vec<(Task, Vec<f32>)> = (0..256)
        .map(|i| (Task::ALL[i % 2], (0..51).map(|_| rng.uniform(-2.0, 2.0) as f32).collect()))
        .collect();
    // Encoder v4, as the shipped actors; the encoder (v5) serves it its 51-feature prefix.
    let meta = ModelMeta { encoder_version: 4, max_speed: 5.0 };
    let bytes = quantize(
        &FloatActor::random(shape, 42),
        meta,
        calibration.iter().map(|(t, f)| (*t, &f[..])),
    )
    .unwrap();
    std::fs::write(out.join("model.skym"), bytes).unwrap();
}
