//! Firmware-shaped example of the onboard core on a Cortex-M7: the model is embedded with
//! `include_bytes!`, decoded in place; a world snapshot arrives as TUNNEL-sized chunks and is
//! reassembled; each herder's observation is encoded and the int8 actor and the safety rules
//! decide its velocity. No heap: the reassembler and the snapshot live in `.bss`.
#![no_std]
#![no_main]

use core::panic::PanicInfo;

use cortex_m_rt::entry;
use skyherd_onboard::actor::Actor;
use skyherd_onboard::obs::{FEATURES, encode_version};
use skyherd_onboard::safety::{self, Limits, Situation};
use skyherd_onboard::wire::{
    MAX_MESSAGE, MAX_TARGETS, Reassembler, Uplink, WorldSnapshot, chunks, decode_uplink,
    encode_uplink,
};
use skyherd_onboard::Task;

static MODEL: &[u8] = include_bytes!(concat!(env!("OUT_DIR"), "/model.skym"));

/// Stands in for the ground station: a 1024-target snapshot, encoded and chunked.
fn ground_snapshot(world: &mut WorldSnapshot) {
    world.sequence = 1;
    world.timestamp_ms = 1_000;
    for i in 0..MAX_TARGETS {
        let (x, y) = ((i % 32) as f32, (i / 32) as f32);
        let _ = world.targets.push([200.0 + 2.5 * x, 150.0 + 2.5 * y]);
    }
    for h in 0..4 {
        let _ = world.herders.push([150.0 + 60.0 * h as f32, 120.0, 2.0]);
    }
}

fn decide(actor: &Actor<'_>, world: &WorldSnapshot, herder: usize) -> [f32; 3] {
    let mut features = [0.0f32; FEATURES];
    // Only the features the model's encoder version reads: an older model skips later passes.
    let version = actor.model().encoder_version;
    let Ok(frame) = encode_version(&world.obs_input(herder), version, &mut features) else {
        return [0.0; 3];
    };
    let velocity = frame.action_to_world(actor.infer(world.task, &features));
    let limits = Limits::arena(world.area, actor.max_speed());
    let situation = Situation {
        position: world.herders[herder],
        velocity,
        snapshot_age_s: 0.0,
        snapshot_finite: world.is_finite(),
        current_velocity: None,
    };
    safety::check(&limits, &situation).velocity
}

#[entry]
fn main() -> ! {
    let (Some(reassembler), Some(sent), Some(received), Some(message)) = (
        cortex_m::singleton!(: Reassembler = Reassembler::new()),
        cortex_m::singleton!(: WorldSnapshot = WorldSnapshot::empty(Task::Driving, [500.0, 500.0, 10.0])),
        cortex_m::singleton!(: Option<Uplink> = None),
        cortex_m::singleton!(: [u8; MAX_MESSAGE] = [0; MAX_MESSAGE]),
    ) else {
        halt()
    };
    let Ok(actor) = Actor::from_bytes(MODEL) else { halt() };

    ground_snapshot(sent);
    if let Ok(bytes) = encode_uplink(&Uplink::Snapshot(sent.clone()), message)
        && let Ok(parts) = chunks(1, bytes)
    {
        for chunk in parts {
            if let Ok(Some(done)) = reassembler.push(chunk.as_bytes()) {
                *received = decode_uplink(done).ok();
            }
        }
    }
    if let Some(Uplink::Snapshot(world)) = received {
        for herder in 0..world.herders.len() {
            core::hint::black_box(decide(&actor, world, herder));
        }
    }
    halt()
}

fn halt() -> ! {
    loop {
        cortex_m::asm::wfi();
    }
}

#[panic_handler]
fn panic(_: &PanicInfo) -> ! {
    halt()
}
