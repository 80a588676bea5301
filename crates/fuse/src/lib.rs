//! Training-free registration of proposal descriptors onto Gaussians via top-K ray weights (paper 3.3)
