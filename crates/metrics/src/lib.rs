//! Evaluation protocols: LERF-OVS selection, ScanNet mIoU/mAcc, proposal clustering and surface distance
