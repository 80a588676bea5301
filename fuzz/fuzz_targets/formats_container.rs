//! The container parser and the reader of whatever kind the metadata names (the path of
//! `profuse inspect`): any bytes give a value or a typed error, never a panic, and no
//! allocation beyond what the data backs (run with -rss_limit_mb=2048).
#![no_main]

use libfuzzer_sys::fuzz_target;
use profuse_formats::{validate_any, Container};

fuzz_target!(|data: &[u8]| {
    if let Ok(c) = Container::from_vec("fuzz.safetensors", data.to_vec()) {
        let _ = validate_any(&c);
    }
});
