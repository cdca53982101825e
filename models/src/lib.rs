//! The skyherd model file format.
#![cfg_attr(not(feature = "std"), no_std)]

/// The two shepherding tasks of the paper; the index selects the task-specific layers.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
#[repr(u8)]
pub enum Task {
    /// Drive a flock from a start circle into the goal circle.
    Driving = 0,
    /// Gather scattered targets into the goal circle.
    Collecting = 1,
}

impl Task {
    /// Number of tasks a model serves.
    pub const COUNT: usize = 2;
    /// Both tasks, in index order.
    pub const ALL: [Task; 2] = [Task::Driving, Task::Collecting];

    /// The task's index into per-task layers.
    pub const fn index(self) -> usize {
        self as usize
    }

    /// The task with the given index, if any.
    pub const fn from_index(index: usize) -> Option<Task> {
        match index {
            0 => Some(Task::Driving),
            1 => Some(Task::Collecting),
            _ => None,
        }
    }
}
