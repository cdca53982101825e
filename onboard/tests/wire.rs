//! Uplink messages: encoding, chunking, and reassembly under loss, reordering and duplication.

use skyherd_model::{SplitMix64, Task};
use skyherd_onboard::wire::{
    CHUNK_DATA, CHUNK_HEADER_LEN, MAX_CHUNKS, MAX_HERDERS, MAX_MESSAGE, MAX_TARGETS, MissionAction,
    MissionCommand, Reassembler, TUNNEL_PAYLOAD, Uplink, WireError, WorldSnapshot, chunks,
    decode_uplink, encode_uplink, parse_chunk,
};

fn snapshot(n: usize, sequence: u32) -> WorldSnapshot {
    let mut s = WorldSnapshot::empty(Task::Collecting, [500.0, 500.0, 10.0]);
    s.sequence = sequence;
    s.timestamp_ms = 1_000 * sequence as u64;
    for i in 0..n {
        s.targets
            .push([i as f32 * 0.37, 499.9 - i as f32 * 0.11])
            .unwrap();
    }
    for i in 0..4 {
        s.herders.push([10.0 * i as f32, 20.0, 2.0]).unwrap();
    }
    s
}

fn encode(message: &Uplink) -> Vec<u8> {
    let mut buffer = [0u8; MAX_MESSAGE];
    encode_uplink(message, &mut buffer).unwrap().to_vec()
}

#[test]
fn largest_snapshot_fits_and_round_trips() {
    let mut s = WorldSnapshot::empty(Task::Driving, [500.0, 500.0, 10.0]);
    s.sequence = u32::MAX;
    s.timestamp_ms = u64::MAX;
    for _ in 0..MAX_TARGETS {
        s.targets.push([f32::MAX, -f32::MAX]).unwrap();
    }
    for _ in 0..MAX_HERDERS {
        s.herders.push([1.0, 2.0, 3.0]).unwrap();
    }
    let bytes = encode(&Uplink::Snapshot(s.clone()));
    assert!(bytes.len() <= MAX_MESSAGE, "{} bytes", bytes.len());
    assert_eq!(bytes.len(), 8624);
    assert_eq!(decode_uplink(&bytes).unwrap(), Uplink::Snapshot(s));
    assert!(chunks(0, &bytes).unwrap().len() <= MAX_CHUNKS);
}

#[test]
fn command_round_trips_in_one_chunk() {
    let c = Uplink::Command(MissionCommand {
        sequence: 3,
        task: Task::Driving,
        goal: [100.0, 400.0],
        goal_radius: 45.0,
        action: MissionAction::Start,
    });
    let bytes = encode(&c);
    let sent: Vec<_> = chunks(9, &bytes).unwrap().collect();
    assert_eq!(sent.len(), 1);
    let mut r = Reassembler::new();
    let got = r.push(sent[0].as_bytes()).unwrap().unwrap();
    assert_eq!(decode_uplink(got).unwrap(), c);
}

#[test]
fn reorder_duplicates_and_loss() {
    let mut rng = SplitMix64::new(1);
    let mut r = Reassembler::new();
    for id in 0..40u16 {
        let message = Uplink::Snapshot(snapshot(1 + (id as usize * 37) % MAX_TARGETS, id as u32));
        let bytes = encode(&message);
        let mut sent: Vec<_> = chunks(id, &bytes).unwrap().collect();
        assert!(sent.iter().all(|c| c.as_bytes().len() <= TUNNEL_PAYLOAD));
        // Shuffle and duplicate some.
        for i in (1..sent.len()).rev() {
            sent.swap(i, (rng.next_u64() % (i as u64 + 1)) as usize);
        }
        let dup = sent[0];
        sent.push(dup);
        let lose = id % 5 == 4 && sent.len() > 2;
        if lose {
            sent.remove(sent.len() / 2);
        }
        let mut done = None;
        for c in &sent {
            match r.push(c.as_bytes()) {
                Ok(Some(m)) => done = Some(decode_uplink(m).unwrap()),
                Ok(None) => {}
                // The duplicate after completion is a chunk of an already-completed message.
                Err(WireError::Stale { message_id }) => assert_eq!(message_id, id),
                Err(e) => panic!("{e}"),
            }
        }
        if lose {
            assert_eq!(done, None);
            assert!(r.progress().is_some());
        } else {
            assert_eq!(done, Some(message));
        }
    }
}

#[test]
fn stale_inconsistent_and_corrupt_chunks() {
    let a = encode(&Uplink::Snapshot(snapshot(300, 1)));
    let b = encode(&Uplink::Snapshot(snapshot(200, 2)));
    let ca: Vec<_> = chunks(10, &a).unwrap().collect();
    let cb: Vec<_> = chunks(11, &b).unwrap().collect();
    let mut r = Reassembler::new();
    assert_eq!(r.push(ca[0].as_bytes()), Ok(None));
    // A newer message abandons the unfinished older one; the older is then stale.
    assert_eq!(r.push(cb[0].as_bytes()), Ok(None));
    assert_eq!(
        r.push(ca[1].as_bytes()),
        Err(WireError::Stale { message_id: 10 })
    );
    // Ids wrap: 2 is newer than 65530.
    let mut w = Reassembler::new();
    let old: Vec<_> = chunks(65530, &a).unwrap().collect();
    let new: Vec<_> = chunks(2, &b).unwrap().collect();
    assert_eq!(w.push(old[0].as_bytes()), Ok(None));
    assert_eq!(w.push(new[0].as_bytes()), Ok(None));
    assert_eq!(w.progress(), Some((1, new.len() as u16)));
    // A flipped data byte with an intact header: every chunk arrives, the CRC catches it.
    let mut r = Reassembler::new();
    let mut result = Ok(None);
    for (i, c) in cb.iter().enumerate() {
        let mut bytes = c.as_bytes().to_vec();
        if i == 1 {
            bytes[CHUNK_HEADER_LEN + 3] ^= 0x40;
        }
        result = r.push(&bytes).map(|m| m.map(<[u8]>::to_vec));
    }
    assert_eq!(result, Err(WireError::CrcMismatch { message_id: 11 }));
    // Malformed chunks.
    let good = cb[0].as_bytes();
    assert_eq!(parse_chunk(&good[..5]), Err(WireError::ChunkLength(5)));
    let mut bad = good.to_vec();
    bad[0] = 0;
    assert_eq!(parse_chunk(&bad), Err(WireError::BadMagic(0)));
    bad[0] = good[0];
    bad[1] = 9;
    assert_eq!(parse_chunk(&bad), Err(WireError::UnsupportedVersion(9)));
    assert_eq!(
        parse_chunk(&good[..good.len() - 1]),
        Err(WireError::BadChunkHeader)
    );
    assert!(chunks(0, &[]).is_err() && chunks(0, &vec![0; MAX_MESSAGE + 1]).is_err());
    assert_eq!(CHUNK_DATA, 114);
}

#[test]
fn decode_errors_are_values() {
    assert!(matches!(decode_uplink(&[]), Err(WireError::Decode(_))));
    assert!(matches!(decode_uplink(&[7]), Err(WireError::Decode(_))));
    let mut bytes = encode(&Uplink::Snapshot(snapshot(3, 1)));
    bytes.push(0);
    assert_eq!(decode_uplink(&bytes), Err(WireError::TrailingBytes(1)));
    // More targets than the capacity: a decode error, not an overflow.
    let mut over = encode(&Uplink::Snapshot(snapshot(0, 1)));
    // [tag, seq, ts, task, herders len, 4 herders (48 bytes), targets len = 0 at the end of that]
    let targets_len_at = 1 + 1 + 2 + 1 + 1 + 48;
    assert_eq!(over[targets_len_at], 0);
    over.splice(targets_len_at..=targets_len_at, [0x81, 0x08]); // varint 1025
    assert!(matches!(decode_uplink(&over), Err(WireError::Decode(_))));
    assert!(
        WireError::Stale { message_id: 3 }
            .to_string()
            .contains("older")
    );
}
