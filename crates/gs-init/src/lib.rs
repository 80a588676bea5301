//! Triangulated 3D Gaussian initialisation from dense or sparse matches (paper 3.1)
