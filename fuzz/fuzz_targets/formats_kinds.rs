//! Each kind's checks without the `format` gate: the first byte picks the kind (17), the
//! rest is the container, read and validated as that kind whatever its metadata says, so
//! mutations reach every kind's shape and value rules.
#![no_main]

use libfuzzer_sys::fuzz_target;
use profuse_formats::{
    Cameras, Container, Features, FileKind, FusePartial, Gaussians, Masks, Matches, Mesh, Pq,
    Prompts, Proposals, Selection, SemanticIndex, SparseMatches, TopK, VertexLabels, ViewMaps,
    WarpPartial,
};

fn check<K: FileKind>(c: &Container) {
    if let Ok(value) = K::from_container(c) {
        if value.validate(c.path()).is_ok() {
            let _ = value.counts();
        }
    }
}

fuzz_target!(|data: &[u8]| {
    let Some((&which, rest)) = data.split_first() else {
        return;
    };
    let Ok(c) = Container::from_vec("fuzz.safetensors", rest.to_vec()) else {
        return;
    };
    match which % 17 {
        0 => check::<Cameras>(&c),
        1 => check::<Gaussians>(&c),
        2 => check::<Masks>(&c),
        3 => check::<Matches>(&c),
        4 => check::<SparseMatches>(&c),
        5 => check::<Proposals>(&c),
        6 => check::<Features>(&c),
        7 => check::<Pq>(&c),
        8 => check::<Prompts>(&c),
        9 => check::<Selection>(&c),
        10 => check::<VertexLabels>(&c),
        11 => check::<Mesh>(&c),
        12 => check::<ViewMaps>(&c),
        13 => check::<TopK>(&c),
        14 => check::<FusePartial>(&c),
        15 => check::<SemanticIndex>(&c),
        _ => check::<WarpPartial>(&c),
    }
});
