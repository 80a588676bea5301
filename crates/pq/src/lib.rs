//! Faiss-compatible product quantisation of Gaussian descriptors with ADC shortlist and exact re-rank (paper 3.4)
