//! Uplink message decoder (postcard): errors are values, never panics.
#![no_main]

use libfuzzer_sys::fuzz_target;
use skyherd_onboard::wire::decode_uplink;

fuzz_target!(|data: &[u8]| {
    let _ = decode_uplink(data);
});
