//! Every decoder against arbitrary bytes: never a panic, always a value. 100,000 cases per
//! decoder (`PROPTEST_CASES` overrides), a few seconds each.

use proptest::prelude::*;
use skyherd_model::format::CRC32;
use skyherd_model::{ActorShape, FloatActor, ModelMeta, SplitMix64, Task, decode, quantize};
use skyherd_onboard::actor::infer_quantized_any;
use skyherd_onboard::wire::{
    MAX_MESSAGE, Reassembler, TUNNEL_PAYLOAD, Uplink, WorldSnapshot, chunks, decode_uplink,
    encode_uplink, parse_chunk,
};

const CASES: u32 = 100_000;

fn config() -> ProptestConfig {
    ProptestConfig {
        cases: std::env::var("PROPTEST_CASES")
            .ok()
            .and_then(|c| c.parse().ok())
            .unwrap_or(CASES),
        failure_persistence: None,
        ..ProptestConfig::default()
    }
}

fn small_model() -> Vec<u8> {
    let shape = ActorShape {
        features: 6,
        hidden: 5,
        shared_layers: 2,
    };
    let mut rng = SplitMix64::new(2);
    let cal: Vec<Vec<f32>> = (0..32)
        .map(|_| (0..6).map(|_| rng.uniform(-1.0, 1.0) as f32).collect())
        .collect();
    let meta = ModelMeta {
        encoder_version: 1,
        max_speed: 5.0,
    };
    quantize(
        &FloatActor::random(shape, 3),
        meta,
        cal.iter().map(|f| (Task::Driving, &f[..])),
    )
    .unwrap()
}

fn message_chunks() -> Vec<Vec<u8>> {
    let mut s = WorldSnapshot::empty(Task::Driving, [500.0, 500.0, 10.0]);
    for i in 0..40 {
        s.targets.push([i as f32, 1.0]).unwrap();
    }
    let mut buffer = [0u8; MAX_MESSAGE];
    let bytes = encode_uplink(&Uplink::Snapshot(s), &mut buffer).unwrap();
    chunks(5, bytes)
        .unwrap()
        .map(|c| c.as_bytes().to_vec())
        .collect()
}

/// Edits: (position, xor mask) pairs, a truncation, and whether to re-seal the CRC.
fn mutate(base: &[u8], edits: &[(usize, u8)], cut: usize, reseal: bool) -> Vec<u8> {
    let mut b = base.to_vec();
    for &(at, mask) in edits {
        let n = b.len();
        b[at % n] ^= mask;
    }
    b.truncate(b.len() - cut % 8);
    if reseal && b.len() >= 8 {
        let n = b.len();
        let len = n as u32;
        b[8..12].copy_from_slice(&len.to_le_bytes());
        let crc = CRC32.checksum(&b[..n - 4]);
        b[n - 4..].copy_from_slice(&crc.to_le_bytes());
    }
    b
}

proptest! {
    #![proptest_config(config())]

    #[test]
    fn model_decode_arbitrary_bytes(bytes in proptest::collection::vec(any::<u8>(), 0..128)) {
        let e = decode(&bytes).unwrap_err();
        prop_assert!(!e.to_string().is_empty());
    }

    #[test]
    fn model_decode_mutated_files(
        edits in proptest::collection::vec((any::<usize>(), any::<u8>()), 0..4),
        cut in any::<usize>(),
        reseal in any::<bool>(),
        features in proptest::collection::vec(any::<f32>(), 6),
    ) {
        thread_local!(static BASE: Vec<u8> = small_model());
        let bytes = BASE.with(|b| mutate(b, &edits, cut, reseal));
        match decode(&bytes) {
            // Whatever decodes must run without panicking.
            Ok(model) => {
                let _ = infer_quantized_any(&model, Task::Collecting, &features);
            }
            Err(e) => prop_assert!(!e.to_string().is_empty()),
        }
    }

    #[test]
    fn chunk_parse_arbitrary_bytes(bytes in proptest::collection::vec(any::<u8>(), 0..160)) {
        if let Ok((header, data)) = parse_chunk(&bytes) {
            prop_assert!(bytes.len() <= TUNNEL_PAYLOAD && header.index < header.count);
            prop_assert!(!data.is_empty());
        }
    }

    #[test]
    fn reassembler_arbitrary_and_mutated_chunks(
        picks in proptest::collection::vec((any::<usize>(), any::<usize>(), any::<u8>()), 1..12),
    ) {
        thread_local!(static CHUNKS: Vec<Vec<u8>> = message_chunks());
        let mut r = Reassembler::new();
        CHUNKS.with(|chunks| {
            for &(which, at, mask) in &picks {
                let mut c = chunks[which % chunks.len()].clone();
                let n = c.len();
                c[at % n] ^= mask;
                if let Ok(Some(m)) = r.push(&c) {
                    let _ = decode_uplink(m);
                }
            }
        });
    }

    #[test]
    fn uplink_decode_arbitrary_bytes(bytes in proptest::collection::vec(any::<u8>(), 0..256)) {
        match decode_uplink(&bytes) {
            Ok(message) => {
                let mut buffer = [0u8; MAX_MESSAGE];
                let again = encode_uplink(&message, &mut buffer).unwrap();
                prop_assert_eq!(decode_uplink(again).unwrap(), message);
            }
            Err(e) => prop_assert!(!e.to_string().is_empty()),
        }
    }
}
