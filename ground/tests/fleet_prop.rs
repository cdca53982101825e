//! Fuzzing that runs in CI, as proptest (cargo-fuzz needs a nightly toolchain; the project pins
//! a stable one): the fleet link's parser and the ground's scan assembler against arbitrary
//! and mutated input, 100,000 cases each (`PROPTEST_CASES` overrides), never a panic.
//!
//! The seed corpus, `tests/corpus/fleet/*.bin`, is real frames from an indoor mission's
//! `.tlog` (heartbeats, positions, the sensor's scans and the ground's acknowledgements, signed
//! with that mission's key); the mutation cases start from them.

use std::path::Path;

use mavlink::dialects::common::{DEBUG_VECT_DATA, MavMessage};
use proptest::prelude::*;
use skyherd_ground::mission::{DroneReport, MissionPlan};
use skyherd_ground::station::{GroundStation, StationConfig};
use skyherd_link::{Codec, Signing, SigningKey};
use skyherd_onboard::Task;

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

fn corpus() -> Vec<Vec<u8>> {
    let dir = Path::new(env!("CARGO_MANIFEST_DIR")).join("tests/corpus/fleet");
    let mut frames: Vec<Vec<u8>> = std::fs::read_dir(&dir)
        .expect("the corpus folder")
        .map(|e| std::fs::read(e.expect("entry").path()).expect("a corpus file"))
        .collect();
    frames.sort();
    assert!(frames.len() >= 10, "corpus has {} frames", frames.len());
    frames
}

fn codecs() -> [Codec; 2] {
    [
        Codec::new(255, 190, None),
        Codec::new(
            255,
            190,
            Some(Signing {
                key: SigningKey([3; 32]),
                link_id: 0,
                accept_unsigned: false,
            }),
        ),
    ]
}

#[test]
fn the_corpus_decodes_whole() {
    let mut codec = Codec::new(255, 190, None);
    let mut out = Vec::new();
    for frame in corpus() {
        codec.decode(&frame, &mut out);
    }
    assert_eq!(out.len(), corpus().len());
    assert_eq!(codec.stats().dropped_frames(), 0);
}

proptest! {
    #![proptest_config(config())]

    #[test]
    fn the_fleet_parser_takes_any_bytes(bytes in proptest::collection::vec(any::<u8>(), 0..700)) {
        for mut codec in codecs() {
            let mut out = Vec::new();
            codec.decode(&bytes, &mut out);
            codec.decode_stream(&bytes, &mut out);
            prop_assert_eq!(codec.stats().frames as usize, out.len());
        }
    }

    #[test]
    fn the_fleet_parser_takes_mutated_corpus_frames(
        picks in proptest::collection::vec(any::<prop::sample::Index>(), 1..4),
        flips in proptest::collection::vec((any::<prop::sample::Index>(), any::<u8>()), 0..6),
        cut in any::<prop::sample::Index>(),
    ) {
        let corpus = corpus();
        let mut datagram: Vec<u8> = picks.iter().flat_map(|i| i.get(&corpus).clone()).collect();
        for (at, value) in &flips {
            let n = datagram.len();
            datagram[at.index(n)] = *value;
        }
        datagram.truncate(cut.index(datagram.len() + 1));
        for mut codec in codecs() {
            let mut out = Vec::new();
            codec.decode(&datagram, &mut out);
            prop_assert_eq!(codec.stats().frames as usize, out.len());
        }
    }

    #[test]
    fn the_scan_assembler_and_station_take_any_debug_vectors(
        messages in proptest::collection::vec(
            (0usize..5, any::<u64>(), any::<f32>(), any::<f32>(), any::<f32>(), any::<bool>()),
            0..60,
        ),
    ) {
        let plan = MissionPlan::new(Task::Driving, [8.0, 8.0], 0.9, [10.0, 10.0, 3.0], vec![1, 2]);
        let mut station = GroundStation::new(StationConfig::new(plan, 0.5)).expect("a station");
        let sensor = u32::from(station.config().sensor_system_id);
        let names = ["det", "det_end", "det_ack", "det_", ""];
        let drones = [DroneReport { system_id: 1, position: Some([1.0, 1.0, 1.0]), last_heard: 0.0 }];
        for (name, time_usec, x, y, z, from_sensor) in messages {
            let message = MavMessage::DEBUG_VECT(DEBUG_VECT_DATA {
                time_usec,
                x,
                y,
                z,
                name: names[name].into(),
            });
            let from = if from_sensor { sensor } else { 77 };
            if let Some(scan) = station.hear(from, &message) {
                // The station may refuse a scan (an error), but never panics on one.
                let _ = station.on_scan(&scan, &drones);
            }
        }
    }
}
