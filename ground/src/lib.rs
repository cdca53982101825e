//! skyherd-ground.
