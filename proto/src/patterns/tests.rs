//! Properties of the generator (PATTERNS.md). The exact bits are pinned by the test vectors in
//! `proto/tests/pattern_vectors.rs`; these tests check what the patterns are *for*: fills,
//! complete scans, orthogonal split pairs, grey-level statistics, statelessness.

use super::*;

fn spec(json: &str) -> PatternSpec {
    serde_json::from_str(json).unwrap_or_else(|e| panic!("{json}: {e}"))
}

fn bits(g: &PatternGenerator, i: u64) -> Vec<u64> {
    let mut w = vec![0u64; g.words_per_pattern()];
    g.fill_bits(i, &mut w).unwrap();
    w
}

fn values(g: &PatternGenerator, i: u64) -> Vec<f32> {
    let mut v = vec![f32::NAN; g.spec().pixels()];
    g.fill_values(i, &mut v);
    v
}

fn bit(words: &[u64], p: usize) -> bool {
    (words[p / 64] >> (p % 64)) & 1 == 1
}

/// Asserts that `hits` successes in `n` Bernoulli(`p`) trials are within `z` standard deviations.
fn assert_binomial(hits: u64, n: u64, p: f64, z: f64, what: &str) {
    let mean = n as f64 * p;
    let sd = (n as f64 * p * (1.0 - p)).sqrt();
    assert!(
        (hits as f64 - mean).abs() <= z * sd + 1.0,
        "{what}: {hits} of {n}, expected {mean:.1} +- {sd:.1} (z = {z})"
    );
}

// --- bernoulli ----------------------------------------------------------------------------------

#[test]
fn bernoulli_fill_is_within_a_binomial_bound() {
    // 61 x 67 = 4087 pixels (not a multiple of 64), 64 patterns from two places in the stream.
    for fill in [0.5, 0.3, 0.95, 0.25, 0.75, 0.1, 0.01, 1.0 / 3.0] {
        let s = PatternSpec::new(Family::Bernoulli { fill }, 61, 67, 2_000_000, 1234).unwrap();
        let q = fill_quantum(fill) as f64 / 65536.0;
        let g = PatternGenerator::new(&s);
        let k = s.pixels();
        let indices: Vec<u64> = (0..32).chain(1_000_000..1_000_032).collect();
        let mut on = 0u64;
        let mut by_bit = [0u64; 64];
        let mut by_bit_n = [0u64; 64];
        let mut pairs_same_pattern = 0u64; // pixels 2m and 2m + 1 both on
        let mut pairs_next_pattern = 0u64; // pixel p on in patterns i and i + 1
        for &i in &indices {
            let w = bits(&g, i);
            let next = bits(&g, i + 1);
            for p in 0..k {
                let b = bit(&w, p);
                on += b as u64;
                by_bit[p % 64] += b as u64;
                by_bit_n[p % 64] += 1;
                pairs_next_pattern += (b && bit(&next, p)) as u64;
                if p % 2 == 0 && p + 1 < k {
                    pairs_same_pattern += (b && bit(&w, p + 1)) as u64;
                }
            }
        }
        let n = (k * indices.len()) as u64;
        assert_binomial(on, n, q, 5.0, &format!("fill {fill}: pixels on"));
        for t in 0..64 {
            assert_binomial(
                by_bit[t],
                by_bit_n[t],
                q,
                5.0,
                &format!("fill {fill}: bit {t}"),
            );
        }
        let pairs = (k / 2) as u64 * indices.len() as u64;
        assert_binomial(
            pairs_same_pattern,
            pairs,
            q * q,
            5.0,
            &format!("fill {fill}: neighbours"),
        );
        assert_binomial(
            pairs_next_pattern,
            n,
            q * q,
            5.0,
            &format!("fill {fill}: next pattern"),
        );
    }
}

#[test]
fn bernoulli_half_is_the_raw_hash_bits() {
    // PATTERNS.md: q = 0.5 uses one word per 64 pixels, unmodified; 0.25 / 0.75 are AND / OR.
    let one = PatternGenerator::new(&spec(
        r#"{"family":"bernoulli","width":8,"height":8,"count":99,"seed":5}"#,
    ));
    for i in [0u64, 1, 2, 98] {
        assert_eq!(bits(&one, i), vec![stream_word(5, i)]);
    }
    let three = PatternGenerator::new(&spec(
        r#"{"family":"bernoulli","width":13,"height":11,"count":99,"seed":5}"#,
    ));
    for i in [0u64, 7] {
        let w = bits(&three, i);
        assert_eq!(w[0], stream_word(5, 3 * i));
        assert_eq!(w[1], stream_word(5, 3 * i + 1));
        assert_eq!(w[2], stream_word(5, 3 * i + 2) & ((1 << (143 - 128)) - 1));
    }
    for (fill, op) in [(0.25, 0), (0.75, 1)] {
        let g = PatternGenerator::new(&spec(&format!(
            r#"{{"family":"bernoulli","width":8,"height":8,"count":99,"seed":5,"fill":{fill}}}"#
        )));
        for i in [0u64, 4] {
            let (a, b) = (stream_word(5, 2 * i), stream_word(5, 2 * i + 1));
            assert_eq!(
                bits(&g, i),
                vec![if op == 0 { a & b } else { a | b }],
                "fill {fill}"
            );
        }
    }
}

#[test]
fn bernoulli_threshold_form_equals_the_recurrence() {
    // The definition in PATTERNS.md (V >= 2^d - odd, V's top bit from word base + 0) against the
    // generator's bit-sliced recurrence, for fills with d = 1..16.
    for q in [
        1u32, 3, 2, 6, 19661, 32768, 16384, 49152, 62259, 65535, 40960, 12345,
    ] {
        let fill = q as f64 / 65536.0;
        let s = PatternSpec::new(Family::Bernoulli { fill }, 10, 10, 50, 77).unwrap();
        let g = PatternGenerator::new(&s);
        let (tz, nw) = (q.trailing_zeros(), 2u64);
        let (d, odd) = (16 - tz, (q >> tz) as u64);
        for i in [0u64, 3, 49] {
            let w = bits(&g, i);
            for p in 0..100usize {
                let (word, t) = (p as u64 / 64, p % 64);
                let base = (i * nw + word) * d as u64;
                let v = (0..d as u64).fold(0u64, |v, j| {
                    (v << 1) | ((stream_word(77, base + j) >> t) & 1)
                });
                assert_eq!(
                    bit(&w, p),
                    v >= (1 << d) - odd,
                    "Q {q} pattern {i} pixel {p}"
                );
            }
        }
    }
}

// --- all binary families --------------------------------------------------------------------

#[test]
fn fill_bits_and_fill_values_agree() {
    for json in [
        r#"{"family":"raster","width":10,"height":7,"count":30,"block":3,"scans":3}"#,
        r#"{"family":"raster","width":64,"height":3,"count":30}"#,
        r#"{"family":"bernoulli","width":13,"height":11,"count":2000000,"seed":9,"fill":0.3}"#,
        r#"{"family":"bernoulli","width":100,"height":37,"count":2000000,"seed":9,"fill":0.95}"#,
        r#"{"family":"hadamard","width":16,"height":4,"count":128,"ordering":"zigzag"}"#,
        r#"{"family":"hadamard","width":2,"height":32,"count":128,"ordering":"cake_cutting"}"#,
    ] {
        let s = spec(json);
        let g = PatternGenerator::new(&s);
        let k = s.pixels();
        for i in [0u64, 1, 2, 5, 29, 127, 1_000_000]
            .into_iter()
            .filter(|&i| i < s.count())
        {
            let w = bits(&g, i);
            let v = values(&g, i);
            for (p, &x) in v.iter().enumerate() {
                assert_eq!(x, bit(&w, p) as u8 as f32, "{json} pattern {i} pixel {p}");
            }
            if !k.is_multiple_of(64) {
                assert_eq!(w[k / 64] >> (k % 64), 0, "{json} pattern {i}: bits past k");
            }
        }
    }
    let speckle = PatternGenerator::new(&spec(
        r#"{"family":"speckle","width":5,"height":4,"count":3}"#,
    ));
    assert_eq!(speckle.fill_bits(0, &mut [0u64]), Err(NotBinary));
}

// --- raster -----------------------------------------------------------------------------------

#[test]
fn raster_scan_lights_each_pixel_exactly_once() {
    for block in [1u32, 3] {
        let s = spec(&format!(
            r#"{{"family":"raster","width":10,"height":7,"count":1000,"block":{block},"scans":84}}"#
        ));
        let g = PatternGenerator::new(&s);
        let (b, bw, bh) = s.raster_grid().unwrap();
        assert_eq!((bw, bh), (10u32.div_ceil(block), 7u32.div_ceil(block)));
        let blocks = (bw * bh) as u64;
        let mut lit = vec![0u32; s.pixels()];
        for i in 0..blocks {
            assert_eq!(g.raster_block(i), Some(i));
            let v = values(&g, i);
            let on: Vec<(usize, usize)> = (0..s.pixels())
                .filter(|&p| v[p] == 1.0)
                .map(|p| (p % 10, p / 10))
                .collect();
            // One block: a rectangle, clipped to the image, at (i % bw, i / bw).
            let (bx, by) = ((i % bw as u64) as usize, (i / bw as u64) as usize);
            let b = b as usize;
            let w = ((bx + 1) * b).min(10) - bx * b;
            let h = ((by + 1) * b).min(7) - by * b;
            assert_eq!(on.len(), w * h, "block {block} pattern {i}");
            assert!(
                on.iter().all(|&(x, y)| x / b == bx && y / b == by),
                "block {block} pattern {i}"
            );
            for (p, x) in v.iter().enumerate() {
                lit[p] += *x as u32;
            }
        }
        assert!(lit.iter().all(|&n| n == 1), "block {block}: {lit:?}");
        // The scan repeats.
        for i in [0u64, 5, blocks - 1] {
            assert_eq!(bits(&g, i), bits(&g, i + blocks));
            assert_eq!(bits(&g, i), bits(&g, i + 7 * blocks));
        }
    }
}

// --- hadamard ---------------------------------------------------------------------------------

/// Sign changes of `h` (P+ as bits) along a line of pixels.
fn changes(w: &[u64], pixels: impl Iterator<Item = usize>) -> u64 {
    let v: Vec<bool> = pixels.map(|p| bit(w, p)).collect();
    v.windows(2).filter(|a| a[0] != a[1]).count() as u64
}

#[test]
fn hadamard_split_pairs_are_orthogonal_for_every_ordering() {
    for (width, height) in [(1u32, 1u32), (8, 8), (16, 4), (2, 32), (32, 32), (4, 64)] {
        let k = (width * height) as usize;
        let mask: Vec<u64> = (0..k.div_ceil(64))
            .map(|w| {
                if (w + 1) * 64 <= k {
                    u64::MAX
                } else {
                    (1u64 << (k % 64)) - 1
                }
            })
            .collect();
        for ordering in HadamardOrdering::ALL {
            let s = PatternSpec::new(
                Family::Hadamard { ordering },
                width,
                height,
                2 * k as u64,
                0,
            )
            .unwrap();
            let g = PatternGenerator::new(&s);
            let mut rows: Vec<Vec<u64>> = Vec::with_capacity(k);
            for r in 0..k as u64 {
                let (plus, minus) = (bits(&g, 2 * r), bits(&g, 2 * r + 1));
                // P+ + P- = 1 everywhere, without overlap.
                for w in 0..mask.len() {
                    assert_eq!(
                        plus[w] & minus[w],
                        0,
                        "{ordering:?} {width}x{height} row {r}"
                    );
                    assert_eq!(
                        plus[w] | minus[w],
                        mask[w],
                        "{ordering:?} {width}x{height} row {r}"
                    );
                }
                assert_eq!(
                    g.split_frame(2 * r).map(|f| (f.row, f.positive)),
                    Some((r, true))
                );
                assert_eq!(
                    g.split_frame(2 * r + 1).map(|f| (f.row, f.positive)),
                    Some((r, false))
                );
                rows.push(plus);
            }
            // The first frame of every ordering is all on (row 0 is the constant function).
            assert_eq!(rows[0], mask, "{ordering:?}");
            // h_a . h_b = k - 2 * (pixels where they differ): k on the diagonal, 0 elsewhere.
            for a in 0..k {
                for b in a..k {
                    let differ: u32 = (0..mask.len())
                        .map(|w| (rows[a][w] ^ rows[b][w]).count_ones())
                        .sum();
                    let dot = k as i64 - 2 * differ as i64;
                    assert_eq!(
                        dot,
                        if a == b { k as i64 } else { 0 },
                        "{ordering:?} {width}x{height} rows {a} {b}"
                    );
                }
            }
        }
    }
}

#[test]
fn hadamard_orderings_follow_their_keys() {
    // Sequencies read off the frames themselves: su = sign changes down column 0, sv = along
    // row 0 (a separable pattern has the same counts on every column / row).
    let bitlen = |x: u64| 64 - x.leading_zeros();
    for (width, height) in [(8u32, 8u32), (16, 4), (4, 16), (32, 2)] {
        let (w, h) = (width as usize, height as usize);
        let k = w * h;
        for ordering in HadamardOrdering::ALL {
            let s = PatternSpec::new(
                Family::Hadamard { ordering },
                width,
                height,
                2 * k as u64,
                0,
            )
            .unwrap();
            let g = PatternGenerator::new(&s);
            let mut keys = Vec::new();
            for r in 0..k as u64 {
                let plus = bits(&g, 2 * r);
                let su = changes(&plus, (0..h).map(|y| y * w));
                let sv = changes(&plus, 0..w);
                for y in 0..h {
                    assert_eq!(
                        changes(&plus, (0..w).map(|x| y * w + x)),
                        sv,
                        "not separable"
                    );
                }
                let key = match ordering {
                    HadamardOrdering::Natural => (g.split_frame(2 * r).unwrap().natural, 0, 0),
                    HadamardOrdering::Sequency => (changes(&plus, 0..k), 0, 0),
                    HadamardOrdering::Zigzag => (su + sv, su, 0),
                    HadamardOrdering::RussianDoll => {
                        (bitlen(su).max(bitlen(sv)) as u64, su + sv, su)
                    }
                    HadamardOrdering::CakeCutting => ((su + 1) * (sv + 1), su, 0),
                };
                if ordering == HadamardOrdering::Sequency {
                    assert_eq!(key.0, r, "sequency row {r} must have {r} sign changes");
                }
                keys.push(key);
            }
            assert!(
                keys.windows(2).all(|p| p[0] < p[1]),
                "{ordering:?} {width}x{height}: keys not strictly increasing: {keys:?}"
            );
        }
    }
}

#[test]
fn russian_doll_prefixes_are_block_constant() {
    // After 4^j rows every measured pattern is constant on (16 / 2^j)-pixel blocks, and the
    // 4^j patterns span all such block images (they are orthogonal, so 4^j of them suffice).
    let s = spec(
        r#"{"family":"hadamard","width":16,"height":16,"count":512,"ordering":"russian_doll"}"#,
    );
    let g = PatternGenerator::new(&s);
    for j in 0..=4u32 {
        let block = 16usize >> j;
        for r in 0..1u64 << (2 * j) {
            let v = values(&g, 2 * r);
            for p in 0..256 {
                let (x, y) = (p % 16, p / 16);
                let corner = (y / block * block) * 16 + x / block * block;
                assert_eq!(v[p], v[corner], "level {j} row {r} pixel {p}");
            }
        }
    }
}

// --- speckle ----------------------------------------------------------------------------------

#[test]
fn speckle_levels_are_24_bit_uniform_on_unit_interval() {
    for grain in [1u32, 3] {
        let s = PatternSpec::new(Family::Speckle { grain }, 64, 48, 2_000_000, 8).unwrap();
        let g = PatternGenerator::new(&s);
        let (g_us, w) = (grain as usize, 64usize);
        let (cw, ch) = (64usize.div_ceil(g_us), 48usize.div_ceil(g_us));
        let (mut sum, mut n, mut low) = (0f64, 0u64, 0u64);
        for i in (0..40u64).chain(1_000_000..1_000_010) {
            let v = values(&g, i);
            for (p, &x) in v.iter().enumerate() {
                assert!((0.0..1.0).contains(&x), "level {x}");
                let l = x * 16_777_216.0;
                assert_eq!(l.fract(), 0.0, "{x} is not a multiple of 2^-24");
                // Constant on each grain x grain cell.
                let (px, py) = (p % w, p / w);
                assert_eq!(x, v[(py / g_us * g_us) * w + px / g_us * g_us]);
            }
            // Statistics over cells (pixels of a cell share one value).
            for cy in 0..ch {
                for cx in 0..cw {
                    let x = v[(cy * g_us) * w + cx * g_us] as f64;
                    sum += x;
                    n += 1;
                    low += (x < 0.25) as u64;
                }
            }
        }
        let mean = sum / n as f64;
        let sd = (1.0 / 12.0 / n as f64).sqrt();
        assert!(
            (mean - 0.5).abs() < 5.0 * sd,
            "grain {grain}: mean {mean} (sd {sd})"
        );
        assert_binomial(
            low,
            n,
            0.25,
            5.0,
            &format!("grain {grain}: levels below 1/4"),
        );
    }
}

#[test]
fn speckle_cells_read_their_own_counter() {
    // PATTERNS.md: L(x, y) = random_word(seed, i * C + cell) >> 40, cells row-major.
    let s =
        spec(r#"{"family":"speckle","width":10,"height":7,"count":2000000,"seed":99,"grain":3}"#);
    let g = PatternGenerator::new(&s);
    for i in [0u64, 1, 1_000_000] {
        let v = values(&g, i);
        assert_eq!(v.len(), 70);
        for (p, &x) in v.iter().enumerate() {
            let cell = (p / 10 / 3) * 4 + (p % 10) / 3;
            let l = stream_word(99, i * 12 + cell as u64) >> 40;
            assert_eq!(x, l as f32 / 16_777_216.0, "pattern {i} pixel {p}");
            assert_eq!(x, speckle_level(stream_word(99, i * 12 + cell as u64)));
        }
    }
}

// --- statelessness ----------------------------------------------------------------------------

const STATELESS_SPECS: [&str; 5] = [
    r#"{"family":"raster","width":10,"height":7,"count":1000,"block":3,"scans":84}"#,
    r#"{"family":"bernoulli","width":13,"height":11,"count":2000000,"seed":3,"fill":0.3}"#,
    r#"{"family":"bernoulli","width":64,"height":64,"count":2000000,"seed":3}"#,
    r#"{"family":"hadamard","width":16,"height":8,"count":256,"ordering":"russian_doll"}"#,
    r#"{"family":"speckle","width":10,"height":7,"count":2000000,"seed":3,"grain":3}"#,
];

fn indices_for(s: &PatternSpec) -> Vec<u64> {
    [0u64, 1, 2, 17, 255, 999, 1_000_000, 1_999_999]
        .into_iter()
        .filter(|&i| i < s.count())
        .collect()
}

#[test]
fn pattern_i_does_not_depend_on_what_was_generated_before() {
    for json in STATELESS_SPECS {
        let s = spec(json);
        let idx = indices_for(&s);
        // Each pattern from a fresh generator...
        let alone: Vec<Vec<f32>> = idx
            .iter()
            .map(|&i| values(&PatternGenerator::new(&s), i))
            .collect();
        // ...equals the same pattern from one generator used forwards, backwards and twice.
        let g = PatternGenerator::new(&s);
        for order in [idx.clone(), idx.iter().rev().copied().collect()] {
            for &i in &order {
                let pos = idx.iter().position(|&x| x == i).unwrap();
                assert_eq!(values(&g, i), alone[pos], "{json} pattern {i}");
                assert_eq!(values(&g, i), alone[pos], "{json} pattern {i} again");
            }
        }
    }
}

#[test]
fn cloned_generators_on_threads_agree() {
    fn is_send_sync<T: Send + Sync>() {}
    is_send_sync::<PatternGenerator>();
    for json in STATELESS_SPECS {
        let s = spec(json);
        let idx = indices_for(&s);
        let g = PatternGenerator::new(&s);
        let expect: Vec<Vec<f32>> = idx.iter().map(|&i| values(&g, i)).collect();
        std::thread::scope(|scope| {
            let handles: Vec<_> = (0..4usize)
                .map(|t| {
                    let (g, idx) = (g.clone(), idx.clone());
                    scope.spawn(move || {
                        // Each thread walks the indices from a different starting point.
                        let n = idx.len();
                        (0..n)
                            .map(|j| (j + t) % n)
                            .map(|j| (j, values(&g, idx[j])))
                            .collect::<Vec<_>>()
                    })
                })
                .collect();
            // And the shared generator, by reference, on another thread at the same time.
            let shared = scope.spawn(|| idx.iter().map(|&i| values(&g, i)).collect::<Vec<_>>());
            for h in handles {
                for (j, v) in h.join().unwrap() {
                    assert_eq!(v, expect[j], "{json} pattern {}", idx[j]);
                }
            }
            assert_eq!(shared.join().unwrap(), expect, "{json}");
        });
    }
}

// --- adaptive -----------------------------------------------------------------------------------

fn adaptive(family: &str, width: u32, indices: &[u32]) -> PatternSpec {
    spec(&format!(
        r#"{{"family":"{family}","width":{width},"height":{width},"count":{}}}"#,
        2 * width * width
    ))
    .with_indices(std::sync::Arc::from(indices.to_vec()))
    .unwrap()
}

/// P+ - P- is the basis function's sign pattern and P+ + P- its support; the Haar functions are
/// orthogonal, the scaling function's pair is (all on, all off).
#[test]
fn adaptive_split_pairs_are_the_basis_functions() {
    let w = 16u32;
    let k = (w * w) as usize;
    let all: Vec<u32> = (0..k as u32).rev().collect();
    for family in ["adaptive_haar", "adaptive_hadamard"] {
        let s = adaptive(family, w, &all);
        let g = PatternGenerator::new(&s);
        let mut signs: Vec<Vec<i32>> = Vec::new();
        for (r, &n) in all.iter().enumerate() {
            let (plus, minus) = (values(&g, 2 * r as u64), values(&g, 2 * r as u64 + 1));
            assert_eq!(bits(&g, 2 * r as u64).len(), 4);
            assert_eq!(g.adaptive_index(2 * r as u64 + 1), Some(n));
            let f = HaarFunction::new(w, n);
            let sign: Vec<i32> = (0..k).map(|p| (plus[p] - minus[p]) as i32).collect();
            for p in 0..k {
                let (x, y) = (p as u32 % w, p as u32 / w);
                let want = if family == "adaptive_haar" {
                    f.sign(x, y)
                } else {
                    adaptive::walsh_sign(w, n, x, y)
                };
                assert_eq!(sign[p], want as i32, "{family} index {n} pixel {p}");
                assert!(plus[p] == 0.0 || minus[p] == 0.0);
            }
            if family == "adaptive_haar" {
                let support = plus
                    .iter()
                    .zip(&minus)
                    .filter(|(a, b)| **a + **b == 1.0)
                    .count();
                assert_eq!(support as u32, f.side() * f.side(), "index {n}");
            } else {
                assert!(plus.iter().zip(&minus).all(|(a, b)| a + b == 1.0));
            }
            signs.push(sign);
        }
        for a in (0..k).step_by(7) {
            for b in 0..k {
                let dot: i32 = signs[a].iter().zip(&signs[b]).map(|(x, y)| x * y).sum();
                if a != b {
                    assert_eq!(dot, 0, "{family}: indices {} {}", all[a], all[b]);
                }
            }
        }
    }
    let haar = PatternGenerator::new(&adaptive("adaptive_haar", 4, &[0]));
    assert_eq!(values(&haar, 0), vec![1.0; 16]);
    assert_eq!(values(&haar, 1), vec![0.0; 16]);
}

/// The Mallat layout: the ring max(r, c) in [2^(m-s), 2^(m-s+1)) has support side 2^s, and the
/// band fixes the split direction.
#[test]
fn haar_indices_follow_the_mallat_layout() {
    let w = 8;
    let f = |r: u32, c: u32| HaarFunction::new(w, r * w + c);
    assert_eq!(f(0, 0).scale, 3);
    assert_eq!(
        (f(0, 1).scale, f(0, 1).split_x, f(0, 1).split_y),
        (3, true, false)
    );
    assert_eq!((f(1, 0).split_x, f(1, 0).split_y), (false, true));
    assert_eq!((f(1, 1).split_x, f(1, 1).split_y), (true, true));
    // Scale 2 (2x2 bands at 2..4): (r, c) = (1, 3) is an x-detail at block (1, 1).
    let g = f(1, 3);
    assert_eq!(
        (g.scale, g.x0, g.y0, g.split_x, g.split_y),
        (2, 4, 4, true, false)
    );
    // Scale 1, diagonal band, last coefficient: the bottom-right 2x2 block.
    let h = f(7, 7);
    assert_eq!(
        (h.scale, h.x0, h.y0, h.split_x, h.split_y),
        (1, 6, 6, true, true)
    );
    assert_eq!(
        [
            h.sign(6, 6),
            h.sign(7, 6),
            h.sign(6, 7),
            h.sign(7, 7),
            h.sign(5, 6)
        ],
        [1, -1, -1, 1, 0]
    );
}

#[test]
#[should_panic(expected = "not resolved")]
fn unresolved_adaptive_specs_have_no_patterns() {
    let s = spec(r#"{"family":"adaptive_haar","width":4,"height":4,"count":8}"#);
    let g = PatternGenerator::new(&s);
    let mut w = vec![0u64; 1];
    let _ = g.fill_bits(0, &mut w);
}

#[test]
#[should_panic(expected = "showed 2 split pairs")]
fn adaptive_frames_past_the_indices_do_not_exist() {
    let g = PatternGenerator::new(&adaptive("adaptive_hadamard", 4, &[3, 0]));
    let mut w = vec![0u64; 1];
    let _ = g.fill_bits(4, &mut w);
}

#[test]
fn single_frame_sessions_show_index_zero_as_its_pair_then_one_positive_frame_an_index() {
    use std::sync::Arc;
    let spec = PatternSpec::new(
        Family::adaptive(true, 0, 0.0, None).with_frames(crate::AdaptiveFrames::Single),
        4,
        4,
        17,
        0,
    )
    .unwrap()
    .with_indices(Arc::from(vec![0u32, 1, 4, 5]))
    .unwrap();
    let pairs = PatternSpec::new(Family::adaptive(true, 0, 0.0, None), 4, 4, 32, 0)
        .unwrap()
        .with_indices(Arc::from(vec![0u32, 1, 4, 5]))
        .unwrap();
    let single = PatternGenerator::new(&spec);
    let paired = PatternGenerator::new(&pairs);
    let bits = |g: &PatternGenerator, i: u64| {
        let mut v = vec![0f32; 16];
        g.fill_values(i, &mut v);
        v
    };
    // Frames 0 and 1: index 0's pair (all on, all off); frame r + 1: the P+ of index r.
    assert_eq!(bits(&single, 0), vec![1.0; 16]);
    assert_eq!(bits(&single, 1), vec![0.0; 16]);
    for (frame, pair_frame) in [(2u64, 2u64), (3, 4), (4, 6)] {
        assert_eq!(
            bits(&single, frame),
            bits(&paired, pair_frame),
            "frame {frame}"
        );
    }
    assert_eq!(
        (0..5).map(|f| single.adaptive_index(f)).collect::<Vec<_>>(),
        [Some(0), Some(0), Some(1), Some(4), Some(5)]
    );
}
