//! Chunk parser and reassembler: the input is split into chunks at length prefixes and pushed
//! in order; nothing may panic, completed messages go through the uplink decoder.
#![no_main]

use libfuzzer_sys::fuzz_target;
use skyherd_onboard::wire::{Reassembler, decode_uplink, parse_chunk};

fuzz_target!(|data: &[u8]| {
    let mut reassembler = Reassembler::new();
    let mut rest = data;
    while let Some((&len, tail)) = rest.split_first() {
        let (chunk, next) = tail.split_at((len as usize).min(tail.len()));
        let _ = parse_chunk(chunk);
        if let Ok(Some(message)) = reassembler.push(chunk) {
            let _ = decode_uplink(message);
        }
        rest = next;
    }
});
