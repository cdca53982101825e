//! skyherd-trainer.
