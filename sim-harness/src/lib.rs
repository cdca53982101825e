//! skyherd-sim.
