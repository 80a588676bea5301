//! 3D Context Proposals: cross-view mask association over warps (paper Algorithm 1)
