//! Mesh-vertex labels from Gaussians with a KD-tree and Mahalanobis gating (paper 4.3)
