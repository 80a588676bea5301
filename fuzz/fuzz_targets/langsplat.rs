//! The LangSplat importer: the input is split by a little-endian u16 length at its start
//! into one view's seg maps (`v_s.npy`) and feature table (`v_f.npy`); the level is the
//! length's top bits.
#![no_main]

use libfuzzer_sys::fuzz_target;
use scene_io::{import_langsplat, LangSplatOptions};

#[path = "scratch.rs"]
mod scratch;

fuzz_target!(|data: &[u8]| {
    if data.len() < 3 {
        return;
    }
    let level = usize::from(data[0] & 3);
    let split = usize::from(u16::from_le_bytes([data[1], data[2]])).min(data.len() - 3);
    let (seg, features) = data[3..].split_at(split);
    let (Some(_), Some(_), Some(dir)) = (
        scratch::write("v_s.npy", seg),
        scratch::write("v_f.npy", features),
        scratch::dir(),
    ) else {
        return;
    };
    let _ = import_langsplat(
        dir,
        &LangSplatOptions {
            level,
            cameras: None,
        },
    );
});
