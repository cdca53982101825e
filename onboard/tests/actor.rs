//! The quantized actor (int8 weights, int16 activations): golden bit-exact vectors, parity with the f32 reference, saturation, checks.

mod common;

use std::fmt::Write as _;
use std::path::PathBuf;

use common::{World, observations, seeded_model};
use skyherd_model::{ActorShape, FloatActor, FormatError, ModelMeta, SplitMix64, Task, quantize};
use skyherd_onboard::actor::{Actor, infer_any, infer_quantized_any};
use skyherd_onboard::obs::{ENCODER_VERSION, FEATURES, V3_FEATURES, V4_FEATURES, feature_count};

const GOLDEN_MODEL: &str = "../models/golden/seeded-f46-h32-s2.skym";
const GOLDEN_VECTORS: &str = "../models/golden/seeded-f46-h32-s2.vectors";

fn path(relative: &str) -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR")).join(relative)
}

/// Inputs of the golden vectors: encoded random worlds, random features and extremes.
fn golden_inputs() -> Vec<(Task, [f32; FEATURES])> {
    let mut inputs = observations(77, 48);
    let mut rng = SplitMix64::new(78);
    for i in 0..12 {
        // The golden model reads encoder v3's features: random values there, zero beyond.
        let mut f = [0.0; FEATURES];
        for x in &mut f[..V3_FEATURES] {
            *x = rng.uniform(-4.0, 4.0) as f32;
        }
        inputs.push((Task::ALL[i % 2], f));
    }
    for task in Task::ALL {
        inputs.push((task, [0.0; FEATURES]));
        inputs.push((task, [1e6; FEATURES]));
        inputs.push((task, [-1e6; FEATURES]));
        inputs.push((
            task,
            std::array::from_fn(|j| if j % 2 == 0 { 3.0 } else { -3.0 }),
        ));
    }
    inputs
}

fn render(actor: &Actor<'_>) -> String {
    let mut text = String::from(
        "# task | 46 input features as f32 bit patterns (hex) | expected int16 output of the task output layer\n",
    );
    for (task, features) in golden_inputs() {
        let bits: Vec<String> = features[..actor.model().features]
            .iter()
            .map(|f| format!("{:08x}", f.to_bits()))
            .collect();
        let q = actor.infer_quantized(task, &features);
        writeln!(
            text,
            "{} | {} | {} {} {}",
            task.index(),
            bits.join(" "),
            q[0],
            q[1],
            q[2]
        )
        .unwrap();
    }
    text
}

#[test]
fn golden_vectors_are_bit_exact() {
    let bytes = std::fs::read(path(GOLDEN_MODEL)).unwrap();
    let actor = Actor::from_bytes(&bytes).unwrap();
    if std::env::var_os("SKYHERD_BLESS").is_some() {
        std::fs::write(path(GOLDEN_VECTORS), render(&actor)).unwrap();
    }
    let golden = std::fs::read_to_string(path(GOLDEN_VECTORS)).unwrap();
    let mut checked = 0;
    for line in golden.lines().filter(|l| !l.starts_with('#')) {
        let parts: Vec<&str> = line.split(" | ").collect();
        let task = Task::from_index(parts[0].parse().unwrap()).unwrap();
        let features: Vec<f32> = parts[1]
            .split(' ')
            .map(|h| f32::from_bits(u32::from_str_radix(h, 16).unwrap()))
            .collect();
        let expected: Vec<i16> = parts[2].split(' ').map(|q| q.parse().unwrap()).collect();
        // The golden model is an encoder-v3 model: it reads the front of today's features.
        assert_eq!(features.len(), V3_FEATURES);
        let mut padded = [0.0f32; FEATURES];
        padded[..V3_FEATURES].copy_from_slice(&features);
        let features = padded;
        assert_eq!(
            actor.infer_quantized(task, &features).to_vec(),
            expected,
            "line: {line:.60}"
        );
        checked += 1;
    }
    assert_eq!(checked, golden_inputs().len());
    // And the vectors must still be what the inputs generate (catches edits to the input set).
    assert_eq!(render(&actor), golden);
}

fn rms(errors: &[f32]) -> f32 {
    (errors.iter().map(|e| e * e).sum::<f32>() / errors.len() as f32).sqrt()
}

fn parity(shape: ActorShape, seed: u64) -> (f32, f32, f32) {
    let (float, bytes) = seeded_model(shape, seed);
    let actor = Actor::from_bytes(&bytes).unwrap();
    let action_errors = |inputs: &[(Task, [f32; FEATURES])]| -> Vec<f32> {
        inputs
            .iter()
            .flat_map(|(task, f)| {
                let q = actor.infer(*task, f);
                let r = float.forward(*task, f);
                (0..3).map(move |k| q[k] - r[k])
            })
            .collect()
    };
    // Recorded-style inputs from worlds the calibration never saw.
    let recorded = observations(seed ^ 99, 1000);
    // Random inputs: each feature uniform between two recorded values of that feature.
    let mut rng = SplitMix64::new(seed ^ 5);
    let random: Vec<(Task, [f32; FEATURES])> = (0..1000)
        .map(|i| {
            let a = &recorded[(rng.next_u64() % 1000) as usize].1;
            let b = &recorded[(rng.next_u64() % 1000) as usize].1;
            let t = rng.uniform(0.0, 1.0) as f32;
            (
                Task::ALL[i % 2],
                std::array::from_fn(|j| a[j] + t * (b[j] - a[j])),
            )
        })
        .collect();
    let (e_rec, e_rand) = (action_errors(&recorded), action_errors(&random));
    let max = e_rec
        .iter()
        .chain(&e_rand)
        .fold(0.0f32, |m, e| m.max(e.abs()));
    (rms(&e_rec), rms(&e_rand), max)
}

/// A normalised action error of 0.01 is 1% of max speed. Measured on seeded random actors
/// (RMS, recorded / random inputs, printed by the test): 0.0014-0.0023 at H=32..128 (format 1,
/// int8 activations and first layer: 0.006-0.010), so the bound asserted is 0.5%.
#[test]
fn quantized_tracks_float_within_half_a_percent_of_max_speed() {
    for (shape, seed, bound) in [
        (
            ActorShape {
                features: FEATURES,
                hidden: 128,
                shared_layers: 2,
            },
            2,
            0.005,
        ),
        (
            ActorShape {
                features: FEATURES,
                hidden: 64,
                shared_layers: 2,
            },
            1,
            0.005,
        ),
        (
            ActorShape {
                features: FEATURES,
                hidden: 32,
                shared_layers: 1,
            },
            3,
            0.005,
        ),
    ] {
        let (recorded, random, max) = parity(shape, seed);
        println!(
            "H={} S={}: RMS action error {recorded:.5} (recorded), {random:.5} (random), max {max:.4}",
            shape.hidden, shape.shared_layers
        );
        assert!(
            recorded <= bound && random <= bound,
            "{shape:?}: {recorded} {random}"
        );
    }
}

#[test]
fn saturates_at_extremes_without_failing() {
    let (float, bytes) = seeded_model(
        ActorShape {
            features: FEATURES,
            hidden: 32,
            shared_layers: 2,
        },
        9,
    );
    let actor = Actor::from_bytes(&bytes).unwrap();
    for task in Task::ALL {
        for x in [
            f32::MAX,
            -f32::MAX,
            1e9,
            -1e9,
            f32::INFINITY,
            f32::NEG_INFINITY,
            f32::NAN,
        ] {
            let a = actor.infer(task, &[x; FEATURES]);
            assert!(
                a.iter().all(|v| v.is_finite() && v.abs() <= 1.0),
                "{x}: {a:?}"
            );
        }
    }
    // An actor pushed hard to one side saturates to (almost) +-1, as the float one does.
    let mut pushed = float.clone();
    for out in &mut pushed.task_outputs {
        out.bias = vec![50.0, -50.0, 50.0];
    }
    let calibration = observations(10, 200);
    let meta = ModelMeta {
        encoder_version: ENCODER_VERSION,
        max_speed: 5.0,
    };
    let bytes = quantize(&pushed, meta, calibration.iter().map(|(t, f)| (*t, &f[..]))).unwrap();
    let actor = Actor::from_bytes(&bytes).unwrap();
    for (task, f) in &calibration {
        let q = actor.infer(*task, f);
        let r = pushed.forward(*task, f);
        assert_eq!(
            actor.infer_quantized(*task, f),
            [i16::MAX, i16::MIN, i16::MAX]
        );
        for k in 0..3 {
            assert!((q[k] - r[k]).abs() < 1e-3, "{q:?} vs {r:?}");
        }
    }
}

#[test]
fn encoder_mismatch_is_an_error() {
    let bytes = model_for(ENCODER_VERSION + 1, FEATURES);
    assert!(matches!(
        Actor::from_bytes(&bytes),
        Err(FormatError::EncoderMismatch { .. })
    ));
    assert!(Actor::from_bytes(&model_for(ENCODER_VERSION, FEATURES)).is_ok());
    // A model for another feature count is refused too.
    let e = Actor::from_bytes(&model_for(ENCODER_VERSION, FEATURES - 1)).unwrap_err();
    assert_eq!(
        e,
        FormatError::EncoderMismatch {
            model: (ENCODER_VERSION, FEATURES as u16 - 1),
            expected: (ENCODER_VERSION, FEATURES as u16)
        }
    );
}

/// Quantizes a seeded actor of `features` inputs for encoder `encoder_version`.
fn model_for(encoder_version: u16, features: usize) -> Vec<u8> {
    let shape = ActorShape {
        features,
        hidden: 16,
        shared_layers: 1,
    };
    let mut rng = SplitMix64::new(21);
    let cal: Vec<Vec<f32>> = (0..64)
        .map(|_| {
            (0..features)
                .map(|_| rng.uniform(-2.0, 2.0) as f32)
                .collect()
        })
        .collect();
    let meta = ModelMeta {
        encoder_version,
        max_speed: 5.0,
    };
    quantize(
        &FloatActor::random(shape, 5),
        meta,
        cal.iter().map(|f| (Task::Driving, &f[..])),
    )
    .unwrap()
}

#[test]
fn models_for_older_encoders_fly_on_the_prefix_of_the_newest_features() {
    // mtddpg-v1 and -v2 were made for encoder v3, whose 46 features v4 keeps in front;
    // mtddpg-v3 and the from-scratch models for v4, whose 51 features v5 keeps in front.
    assert_eq!(feature_count(3), Some(V3_FEATURES));
    assert_eq!(feature_count(4), Some(V4_FEATURES));
    assert_eq!(feature_count(ENCODER_VERSION), Some(FEATURES));
    assert_eq!(feature_count(2), None);
    for (version, width) in [(3, V3_FEATURES), (4, V4_FEATURES)] {
        let bytes = model_for(version, width);
        let actor = Actor::from_bytes(&bytes).expect("an older model loads");
        let mut features = [0.0f32; FEATURES];
        let mut rng = SplitMix64::new(9);
        for f in features.iter_mut() {
            *f = rng.uniform(-1.0, 1.0) as f32;
        }
        let a = actor.infer(Task::Driving, &features);
        // The newer features do not reach an older model.
        features[width..].fill(123.0);
        assert_eq!(actor.infer(Task::Driving, &features), a, "v{version}");
    }
    // Each version's model must have that version's width.
    for (version, width, wrong) in [
        (3, V3_FEATURES, FEATURES),
        (4, V4_FEATURES, V3_FEATURES),
        (4, V4_FEATURES, FEATURES),
        (ENCODER_VERSION, FEATURES, V4_FEATURES),
    ] {
        assert_eq!(
            Actor::from_bytes(&model_for(version, wrong)).unwrap_err(),
            FormatError::EncoderMismatch {
                model: (version, wrong as u16),
                expected: (version, width as u16)
            },
            "v{version} with {wrong} features"
        );
    }
}

#[test]
fn generic_path_serves_any_input_length_and_capacity() {
    // The free functions take any model [`decode`] accepts, up to the capacities.
    for (features, hidden, shared) in [(1, 1, 0), (7, 5, 3), (256, 256, 1)] {
        let shape = ActorShape {
            features,
            hidden,
            shared_layers: shared,
        };
        let float = FloatActor::random(shape, 4);
        let mut rng = SplitMix64::new(8);
        let cal: Vec<Vec<f32>> = (0..50)
            .map(|_| {
                (0..features)
                    .map(|_| rng.uniform(-1.0, 1.0) as f32)
                    .collect()
            })
            .collect();
        let meta = ModelMeta {
            encoder_version: 1,
            max_speed: 3.0,
        };
        let bytes = quantize(&float, meta, cal.iter().map(|f| (Task::Collecting, &f[..]))).unwrap();
        let model = skyherd_model::decode(&bytes).unwrap();
        for f in &cal {
            let q = infer_any(&model, Task::Collecting, f);
            let r = float.forward(Task::Collecting, f);
            assert!(
                (0..3).all(|k| (q[k] - r[k]).abs() < 0.1),
                "{features}x{hidden}: {q:?} {r:?}"
            );
            // Too short and too long inputs are read as zero-padded / truncated, never a panic.
            let _ = infer_quantized_any(&model, Task::Driving, &f[..features / 2]);
            let _ = infer_quantized_any(&model, Task::Driving, &[0.0; 300]);
        }
    }
}

#[test]
fn recorded_worlds_give_actions_in_range() {
    let (_, bytes) = seeded_model(
        ActorShape {
            features: FEATURES,
            hidden: 32,
            shared_layers: 2,
        },
        12,
    );
    let actor = Actor::from_bytes(&bytes).unwrap();
    let mut rng = SplitMix64::new(3);
    for n in [1, 16, 256, 1024] {
        let world = World::random(&mut rng, n, 4);
        let a = actor.infer(world.task, &world.features(0));
        assert!(a.iter().all(|v| v.abs() <= 1.0));
    }
}
