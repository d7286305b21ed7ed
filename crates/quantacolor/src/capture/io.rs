//! Atomic file output and `.npy` helpers shared by every writer.
