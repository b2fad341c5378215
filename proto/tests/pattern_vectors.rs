//! The Rust generator against the test vectors of `proto/PATTERNS.md`.
//!
//! `pattern_vectors.json` is produced by `python3 proto/tools/patterns_ref.py`, an independent
//! implementation written from PATTERNS.md. Every pattern, hash, random word, fill quantum,
//! ordering table and wire encoding in it must be reproduced exactly: if this test fails, either
//! the generator changed (which breaks every lab's projector code) or the document is wrong.

use helmholtz_proto::patterns::rng::stream_word;
use helmholtz_proto::patterns::{FILL_BITS, HadamardPlan, fill_quantum};
use helmholtz_proto::wire::{decode_values, encode_values};
use helmholtz_proto::{Family, HadamardOrdering, PatternGenerator, PatternSpec};
use serde_json::Value;

const VECTORS: &str = include_str!("pattern_vectors.json");

fn vectors() -> Value {
    let v: Value = serde_json::from_str(VECTORS).expect("pattern_vectors.json parses");
    assert_eq!(v["format"], "helmholtz-pattern-vectors/1");
    v
}

fn array<'a>(v: &'a Value, key: &str) -> &'a Vec<Value> {
    v[key]
        .as_array()
        .unwrap_or_else(|| panic!("`{key}` is not an array"))
}

fn u64_of(v: &Value, key: &str) -> u64 {
    v[key]
        .as_u64()
        .unwrap_or_else(|| panic!("`{key}` is not a u64: {}", v[key]))
}

fn str_of<'a>(v: &'a Value, key: &str) -> &'a str {
    v[key]
        .as_str()
        .unwrap_or_else(|| panic!("`{key}` is not a string: {}", v[key]))
}

fn hex(bytes: &[u8]) -> String {
    bytes.iter().map(|b| format!("{b:02x}")).collect()
}

fn words_le_bytes(words: &[u64]) -> Vec<u8> {
    words.iter().flat_map(|w| w.to_le_bytes()).collect()
}

// --- SHA-256 (FIPS 180-4), so that the runs need no extra dependency -------------------------

const K256: [u32; 64] = [
    0x428a2f98, 0x71374491, 0xb5c0fbcf, 0xe9b5dba5, 0x3956c25b, 0x59f111f1, 0x923f82a4, 0xab1c5ed5,
    0xd807aa98, 0x12835b01, 0x243185be, 0x550c7dc3, 0x72be5d74, 0x80deb1fe, 0x9bdc06a7, 0xc19bf174,
    0xe49b69c1, 0xefbe4786, 0x0fc19dc6, 0x240ca1cc, 0x2de92c6f, 0x4a7484aa, 0x5cb0a9dc, 0x76f988da,
    0x983e5152, 0xa831c66d, 0xb00327c8, 0xbf597fc7, 0xc6e00bf3, 0xd5a79147, 0x06ca6351, 0x14292967,
    0x27b70a85, 0x2e1b2138, 0x4d2c6dfc, 0x53380d13, 0x650a7354, 0x766a0abb, 0x81c2c92e, 0x92722c85,
    0xa2bfe8a1, 0xa81a664b, 0xc24b8b70, 0xc76c51a3, 0xd192e819, 0xd6990624, 0xf40e3585, 0x106aa070,
    0x19a4c116, 0x1e376c08, 0x2748774c, 0x34b0bcb5, 0x391c0cb3, 0x4ed8aa4a, 0x5b9cca4f, 0x682e6ff3,
    0x748f82ee, 0x78a5636f, 0x84c87814, 0x8cc70208, 0x90befffa, 0xa4506ceb, 0xbef9a3f7, 0xc67178f2,
];

fn sha256(data: &[u8]) -> String {
    let mut h: [u32; 8] = [
        0x6a09e667, 0xbb67ae85, 0x3c6ef372, 0xa54ff53a, 0x510e527f, 0x9b05688c, 0x1f83d9ab,
        0x5be0cd19,
    ];
    let mut msg = data.to_vec();
    msg.push(0x80);
    while msg.len() % 64 != 56 {
        msg.push(0);
    }
    msg.extend_from_slice(&((data.len() as u64) * 8).to_be_bytes());
    for block in msg.chunks_exact(64) {
        let mut w = [0u32; 64];
        for t in 0..16 {
            w[t] = u32::from_be_bytes(block[4 * t..4 * t + 4].try_into().unwrap());
        }
        for t in 16..64 {
            let s0 = w[t - 15].rotate_right(7) ^ w[t - 15].rotate_right(18) ^ (w[t - 15] >> 3);
            let s1 = w[t - 2].rotate_right(17) ^ w[t - 2].rotate_right(19) ^ (w[t - 2] >> 10);
            w[t] = w[t - 16]
                .wrapping_add(s0)
                .wrapping_add(w[t - 7])
                .wrapping_add(s1);
        }
        let [mut a, mut b, mut c, mut d, mut e, mut f, mut g, mut hh] = h;
        for t in 0..64 {
            let s1 = e.rotate_right(6) ^ e.rotate_right(11) ^ e.rotate_right(25);
            let ch = (e & f) ^ (!e & g);
            let t1 = hh
                .wrapping_add(s1)
                .wrapping_add(ch)
                .wrapping_add(K256[t])
                .wrapping_add(w[t]);
            let s0 = a.rotate_right(2) ^ a.rotate_right(13) ^ a.rotate_right(22);
            let maj = (a & b) ^ (a & c) ^ (b & c);
            let t2 = s0.wrapping_add(maj);
            (hh, g, f, e, d, c, b, a) = (g, f, e, d.wrapping_add(t1), c, b, a, t1.wrapping_add(t2));
        }
        for (x, y) in h.iter_mut().zip([a, b, c, d, e, f, g, hh]) {
            *x = x.wrapping_add(y);
        }
    }
    h.iter().map(|x| format!("{x:08x}")).collect()
}

#[test]
fn sha256_is_fips_180_4() {
    assert_eq!(
        sha256(b"abc"),
        "ba7816bf8f01cfea414140de5dae2223b00361a396177a9cb410ff61f20015ad"
    );
    assert_eq!(
        sha256(b""),
        "e3b0c44298fc1c149afbf4c8996fb92427ae41e4649b934ca495991b7852b855"
    );
    let long = b"abcdbcdecdefdefgefghfghighijhijkijkljklmklmnlmnomnopnopq";
    assert_eq!(
        sha256(long),
        "248d6a61d20638b8e5c026930c3e6039a33ce45964ff2167f6ecedd419db06c1"
    );
}

// --- the pieces ---------------------------------------------------------------------------------

#[test]
fn random_words() {
    let v = vectors();
    let cases = array(&v, "random_words");
    assert!(cases.len() >= 5);
    for c in cases {
        let (seed, counter) = (u64_of(c, "seed"), u64_of(c, "counter"));
        let expect = u64::from_str_radix(str_of(c, "word"), 16).unwrap();
        assert_eq!(
            stream_word(seed, counter),
            expect,
            "random_word({seed}, {counter})"
        );
    }
}

#[test]
fn fill_quanta() {
    let v = vectors();
    let cases = array(&v, "fills");
    assert!(cases.len() >= 10);
    for c in cases {
        let bits = u64::from_str_radix(str_of(c, "fill_f64"), 16).unwrap();
        let fill = f64::from_bits(bits);
        assert_eq!(
            c["fill"].as_f64(),
            Some(fill),
            "serde_json parses {} exactly",
            c["fill"]
        );
        let q = fill_quantum(fill);
        assert_eq!(q as u64, u64_of(c, "quantum"), "fill {fill:e}");
        let tz = q.trailing_zeros();
        assert_eq!(
            (FILL_BITS - tz) as u64,
            u64_of(c, "digits"),
            "fill {fill:e}"
        );
        assert_eq!((q >> tz) as u64, u64_of(c, "odd"), "fill {fill:e}");
        let spec = PatternSpec::new(Family::Bernoulli { fill }, 8, 8, 8, 0).unwrap();
        let canonical = q as f64 / (1u64 << FILL_BITS) as f64;
        assert_eq!(
            spec.family(),
            &Family::Bernoulli { fill: canonical },
            "fill {fill:e}"
        );
        // serde_json (without its `float_roundtrip` feature) may read the 16-17 digit canonical
        // fill one ulp off; re-quantising absorbs that, so compare quanta, not the f64.
        let listed = c["canonical_fill"].as_f64().unwrap();
        assert_eq!(fill_quantum(listed), q, "canonical_fill {listed}");
    }
}

#[test]
fn hadamard_ordering_tables() {
    let v = vectors();
    let cases = array(&v, "orderings");
    for c in cases {
        let (w, h) = (u64_of(c, "width") as u32, u64_of(c, "height") as u32);
        let ordering: HadamardOrdering = serde_json::from_value(c["ordering"].clone()).unwrap();
        let plan = HadamardPlan::new(w, h, ordering);
        let table: Vec<u64> = array(c, "natural")
            .iter()
            .map(|n| n.as_u64().unwrap())
            .collect();
        assert_eq!(table.len() as u32, w * h);
        let ours: Vec<u64> = (0..table.len() as u64)
            .map(|r| plan.natural_index(r))
            .collect();
        assert_eq!(ours, table, "{w}x{h} {ordering:?}");
    }
    for ordering in HadamardOrdering::ALL {
        assert!(
            cases.iter().any(|c| c["ordering"] == ordering.name()),
            "no ordering table for {ordering:?}"
        );
    }
}

#[test]
fn wire_encoding() {
    let v = vectors();
    for c in array(&v, "wire") {
        let values: Vec<f64> = array(c, "values")
            .iter()
            .map(|x| x.as_f64().unwrap())
            .collect();
        let channels = u64_of(c, "channels") as usize;
        let (bytes, crc) = encode_values(&values);
        assert_eq!(hex(&bytes), str_of(c, "bytes_hex"), "{values:?}");
        assert_eq!(format!("{crc:08x}"), str_of(c, "crc32c"), "{values:?}");
        assert_eq!(decode_values(&bytes, channels, crc).unwrap(), values);
    }
}

// --- the patterns -------------------------------------------------------------------------------

/// Pattern `i` as packed bits, checking on the way that `fill_values` shows the same pixels.
fn bits_of(g: &PatternGenerator, i: u64, name: &str) -> Vec<u64> {
    let mut words = vec![0u64; g.words_per_pattern()];
    g.fill_bits(i, &mut words)
        .unwrap_or_else(|e| panic!("{name}: pattern {i}: {e}"));
    let mut values = vec![f32::NAN; g.spec().pixels()];
    g.fill_values(i, &mut values);
    for (p, &v) in values.iter().enumerate() {
        let bit = (words[p / 64] >> (p % 64)) & 1;
        assert_eq!(
            v, bit as f32,
            "{name}: pattern {i} pixel {p}: fill_values vs fill_bits"
        );
    }
    words
}

/// Speckle pattern `i` as 24-bit levels, checking that every value is exactly L / 2^24.
fn levels_of(g: &PatternGenerator, i: u64, name: &str) -> Vec<u32> {
    let mut words = vec![0u64; g.words_per_pattern()];
    assert!(
        g.fill_bits(i, &mut words).is_err(),
        "{name}: speckle must refuse fill_bits"
    );
    let mut values = vec![f32::NAN; g.spec().pixels()];
    g.fill_values(i, &mut values);
    values
        .iter()
        .enumerate()
        .map(|(p, &v)| {
            let scaled = v * 16_777_216.0;
            assert!(
                (0.0..16_777_216.0).contains(&scaled) && scaled.fract() == 0.0,
                "{name}: pattern {i} pixel {p}: {v} is not a 24-bit level"
            );
            scaled as u32
        })
        .collect()
}

fn check_vector(vec: &Value) -> &str {
    let name = str_of(vec, "name");
    let spec: PatternSpec = serde_json::from_value(vec["input"].clone())
        .unwrap_or_else(|e| panic!("{name}: input refused: {e}"));
    let canonical: PatternSpec = serde_json::from_value(vec["spec"].clone())
        .unwrap_or_else(|e| panic!("{name}: canonical spec refused: {e}"));
    assert_eq!(
        spec, canonical,
        "{name}: input does not canonicalise to spec"
    );
    // The canonical JSON, field by field; `fill` through its quantum (see `fill_quanta`).
    let mut ours = serde_json::to_value(&spec).unwrap();
    let mut theirs = vec["spec"].clone();
    let (our_fill, their_fill) = (ours["fill"].take(), theirs["fill"].take());
    assert_eq!(ours, theirs, "{name}: canonical JSON");
    if let Family::Bernoulli { .. } = spec.family() {
        let q = u64_of(vec, "fill_quantum");
        assert_eq!(
            our_fill.as_f64(),
            Some(q as f64 / 65536.0),
            "{name}: canonical fill"
        );
        assert_eq!(
            fill_quantum(their_fill.as_f64().unwrap()) as u64,
            q,
            "{name}"
        );
    }
    assert_eq!(spec.pixels() as u64, u64_of(vec, "pixels"), "{name}");
    // An adaptive session's patterns need its index sequence.
    let spec = if spec.is_adaptive() {
        let basis: Vec<u32> = array(vec, "basis_indices")
            .iter()
            .map(|n| n.as_u64().unwrap() as u32)
            .collect();
        spec.with_indices(basis.into())
            .unwrap_or_else(|e| panic!("{name}: basis_indices refused: {e}"))
    } else {
        spec
    };
    let g = PatternGenerator::new(&spec);
    assert_eq!(
        g.words_per_pattern() as u64,
        u64_of(vec, "words_per_pattern"),
        "{name}"
    );
    if let Family::Bernoulli { fill } = spec.family() {
        assert_eq!(
            fill_quantum(*fill) as u64,
            u64_of(vec, "fill_quantum"),
            "{name}"
        );
    }

    let patterns = array(vec, "patterns");
    assert!(!patterns.is_empty(), "{name}: no patterns");
    for pat in patterns {
        let i = u64_of(pat, "index");
        match spec.family() {
            Family::Speckle { .. } => {
                let expect: Vec<u32> = array(pat, "levels")
                    .iter()
                    .map(|l| l.as_u64().unwrap() as u32)
                    .collect();
                assert_eq!(levels_of(&g, i, name), expect, "{name}: pattern {i} levels");
            }
            family => {
                let words = bits_of(&g, i, name);
                assert_eq!(
                    hex(&words_le_bytes(&words)),
                    str_of(pat, "bits_hex"),
                    "{name}: pattern {i} bits"
                );
                match family {
                    Family::Raster { .. } => {
                        assert_eq!(g.raster_block(i), Some(u64_of(pat, "block")), "{name}: {i}")
                    }
                    Family::Hadamard { .. } => {
                        let f = g.split_frame(i).unwrap();
                        assert_eq!(f.row, u64_of(pat, "row"), "{name}: frame {i} row");
                        assert_eq!(
                            f.natural,
                            u64_of(pat, "natural"),
                            "{name}: frame {i} natural"
                        );
                        assert_eq!(
                            Some(f.positive),
                            pat["positive"].as_bool(),
                            "{name}: frame {i}"
                        );
                    }
                    Family::AdaptiveHaar { .. } | Family::AdaptiveHadamard { .. } => {
                        // Which index of the sequence the frame shows, and which half.
                        let (position, positive) =
                            helmholtz_proto::patterns::adaptive_frame(spec.adaptive_single(), i);
                        assert_eq!(position, u64_of(pat, "pair"), "{name}: frame {i}");
                        assert_eq!(
                            g.adaptive_index(i).map(u64::from),
                            Some(u64_of(pat, "basis_index")),
                            "{name}: frame {i} basis index"
                        );
                        assert_eq!(
                            Some(positive),
                            pat["positive"].as_bool(),
                            "{name}: frame {i}"
                        );
                    }
                    _ => {}
                }
            }
        }
    }

    for run in array(vec, "runs") {
        let (start, count) = (u64_of(run, "start"), u64_of(run, "count"));
        let mut bytes = Vec::new();
        for i in start..start + count {
            if spec.family().is_binary() {
                bytes.extend(words_le_bytes(&bits_of(&g, i, name)));
            } else {
                bytes.extend(levels_of(&g, i, name).iter().flat_map(|l| l.to_le_bytes()));
            }
        }
        assert_eq!(
            sha256(&bytes),
            str_of(run, "sha256"),
            "{name}: run {start}..+{count}"
        );
    }
    name
}

#[test]
fn every_vector_is_reproduced() {
    let v = vectors();
    let all = array(&v, "vectors");
    let names: Vec<&str> = all.iter().map(check_vector).collect();
    assert_eq!(names.len(), all.len());
}

/// The vectors must keep covering what PATTERNS.md promises; trimming the file fails here.
#[test]
fn vectors_cover_the_contract() {
    let v = vectors();
    let specs: Vec<(PatternSpec, Vec<u64>)> = array(&v, "vectors")
        .iter()
        .map(|vec| {
            let spec = serde_json::from_value(vec["spec"].clone()).unwrap();
            let idx = array(vec, "patterns")
                .iter()
                .map(|p| u64_of(p, "index"))
                .collect();
            (spec, idx)
        })
        .collect();
    let any = |f: &dyn Fn(&PatternSpec, &[u64]) -> bool| specs.iter().any(|(s, i)| f(s, i));

    for ordering in HadamardOrdering::ALL {
        assert!(
            any(&|s, _| s.family() == &Family::Hadamard { ordering }
                && s.width() != s.height()
                && s.count() == 2 * s.pixels() as u64),
            "complete non-square hadamard set for {ordering:?}"
        );
    }
    for q in [32768u32, 19661, 62259, 16384, 49152, 1, 3] {
        assert!(
            any(
                &|s, _| matches!(s.family(), Family::Bernoulli { fill } if fill_quantum(*fill) == q)
            ),
            "bernoulli with Q = {q}"
        );
    }
    assert!(any(&|s, i| matches!(s.family(), Family::Bernoulli { .. })
        && s.pixels() % 64 != 0
        && i.iter().any(|&i| i >= 1_000_000)));
    assert!(any(
        &|s, _| matches!(s.family(), Family::Bernoulli { .. }) && s.seed() == u64::MAX
    ));
    assert!(any(
        &|s, _| matches!(*s.family(), Family::Raster { block, .. } if block > 1
        && (s.width() % block != 0 && s.height() % block != 0))
    ));
    assert!(any(
        &|s, i| matches!(s.family(), Family::Raster { .. }) && i.iter().any(|&i| g_blocks(s) <= i)
    ));
    assert!(any(
        &|s, i| s.family() == &Family::Speckle { grain: 3 } && i.contains(&1_000_000)
    ));
    assert!(any(
        &|s, _| matches!(s.family(), Family::Speckle { .. }) && s.seed() == u64::MAX
    ));
    for family in ["adaptive_haar", "adaptive_hadamard"] {
        assert!(
            any(&|s, _| s.family().name() == family
                && s.width() == 16
                && s.count() == 2 * s.pixels() as u64),
            "complete {family} set"
        );
        assert!(
            any(&|s, _| s.family().name() == family
                && s.family()
                    .adaptive_params()
                    .is_some_and(|(b, t)| b > 0 && t > 0.0)),
            "{family} with a batch and a target error"
        );
    }
    assert!(
        any(&|s, _| s.adaptive_single() && s.count() == s.pixels() as u64 + 1),
        "a complete single-frame set"
    );
    assert_eq!(array(&v, "adaptive_replays").len(), 30);
}

fn g_blocks(s: &PatternSpec) -> u64 {
    let (_, bx, by) = s.raster_grid().unwrap();
    bx as u64 * by as u64
}

/// The independent Python implementation still reproduces the committed vectors (so the JSON
/// was not edited by hand and PATTERNS.md, the script and the generator agree). Needs python3,
/// which the project's machines have (`.ci/run` sees to it); without it the test fails, saying so.
#[test]
fn python_reference_reproduces_the_committed_vectors() {
    let dir = env!("CARGO_MANIFEST_DIR");
    let out = match std::process::Command::new("python3")
        .arg(format!("{dir}/tools/patterns_ref.py"))
        .arg("--check")
        .arg(format!("{dir}/tests/pattern_vectors.json"))
        .output()
    {
        Ok(out) => out,
        Err(e) => panic!(
            "python3 is not runnable ({e}): this test runs tools/patterns_ref.py, the independent Python \
             reference of PATTERNS.md; install Python 3 (Debian: apt-get install python3) or put python3 on PATH"
        ),
    };
    assert!(
        out.status.success(),
        "patterns_ref.py --check failed:\n{}{}",
        String::from_utf8_lossy(&out.stdout),
        String::from_utf8_lossy(&out.stderr)
    );
}
