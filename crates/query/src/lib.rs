//! Open-vocabulary 3D selection: prompt scores, active sets, per-view activation masks (paper 3.4)
