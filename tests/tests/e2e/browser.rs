//! The web viewer in a real browser: the real `helmholtz-demo` (the service and its simulated
//! rigs) on 127.0.0.1 port 0 with a real SQLite file (or PostgreSQL with
//! `HELMHOLTZ_TEST_BACKEND=postgres`), and a headless Chromium driven through chromedriver
//! (`helmholtz_tests::browser`). Nothing is mocked: the browser loads the page the server
//! serves and calls its REST API with the demo's reader token.
//!
//! What a user does: log in with a token (pasted, and through the demo's `/#token=` link), see
//! the demo's sessions, open a dual image (zoom, side by side), drag a light on the camera's view
//! and see the relit image change (100 drags, timed in the browser: the figures go to
//! `target/browser-artefacts/relight-latency.json` and docs/web-viewer.md, never asserted),
//! predict a stored frame, start a reconstruction and cancel it while its progress streams in,
//! and see another lab's session refused. Screenshots: `target/browser-artefacts/*.png`.
//!
//! Chromium and chromedriver must be installed (`apt-get install chromium chromium-driver`;
//! .ci/run does it); without them the test fails saying so.

use std::io::{BufRead, BufReader};
use std::path::PathBuf;
use std::process::{Child, Command, Stdio};
use std::time::{Duration, Instant};

use helmholtz_tests::browser::Browser;
use helmholtz_tests::{backend, binary, create_token_on, store_args};
use serde_json::{Value, json};

const WAIT: Duration = Duration::from_secs(60);

/// `target/browser-artefacts` (screenshots, the latency figures).
fn artefacts() -> PathBuf {
    let exe = std::env::current_exe().unwrap();
    // target/<profile>/deps/browser-HASH
    let target = exe.ancestors().nth(3).unwrap().to_path_buf();
    target.join("browser-artefacts")
}

/// The demo, serving after it has uploaded and reconstructed its sessions.
struct Demo {
    child: Child,
    base: String,
    reader: String,
    rig: String,
    viewer_link: String,
}

impl Drop for Demo {
    fn drop(&mut self) {
        let _ = self.child.kill();
        let _ = self.child.wait();
    }
}

fn start_demo(data: &std::path::Path) -> Demo {
    let mut child = Command::new(binary("helmholtz-demo"))
        .args(["--listen", "127.0.0.1:0"])
        .args(store_args(data))
        .env("RUST_LOG", "warn")
        .stdin(Stdio::null())
        .stdout(Stdio::piped())
        .stderr(Stdio::inherit())
        .spawn()
        .expect("starting helmholtz-demo");
    let stdout = child.stdout.take().unwrap();
    let (tx, rx) = std::sync::mpsc::channel::<String>();
    std::thread::spawn(move || {
        for line in BufReader::new(stdout).lines() {
            let Ok(line) = line else { break };
            if tx.send(line).is_err() {
                break;
            }
        }
    });
    let deadline = Instant::now() + Duration::from_secs(600);
    let mut seen = Vec::new();
    loop {
        let line = rx
            .recv_timeout(deadline.saturating_duration_since(Instant::now()))
            .unwrap_or_else(|_| panic!("the demo did not finish:\n{}", seen.join("\n")));
        let done = line.starts_with("Serving on ");
        seen.push(line);
        if done {
            break;
        }
    }
    let text = seen.join("\n");
    let field = |prefix: &str| -> String {
        let line = seen
            .iter()
            .find(|l| l.trim_start().starts_with(prefix))
            .unwrap_or_else(|| panic!("no line {prefix:?} in:\n{text}"));
        line.split_whitespace().last().unwrap().to_string()
    };
    let reader = field("reader (");
    let rig = field("rig ");
    let viewer_link = field("viewer (");
    let base = viewer_link.split("/#token=").next().unwrap().to_string();
    assert_eq!(
        viewer_link,
        format!("{base}/#token={reader}"),
        "the demo's viewer link carries the reader token in the fragment"
    );
    Demo {
        child,
        base,
        reader,
        rig,
        viewer_link,
    }
}

/// Waits (up to [`WAIT`]) until reconstruction `id` is done; its last view.
async fn wait_done(client: &reqwest::Client, base: &str, token: &str, id: i64) -> Value {
    let deadline = Instant::now() + WAIT;
    loop {
        let v: Value = client
            .get(format!("{base}/v1/reconstructions/{id}"))
            .bearer_auth(token)
            .send()
            .await
            .unwrap()
            .json()
            .await
            .unwrap();
        if v["state"] == "done" {
            return v;
        }
        assert!(Instant::now() < deadline, "{v}");
        tokio::time::sleep(Duration::from_millis(50)).await;
    }
}

fn median_p95(mut v: Vec<f64>) -> (f64, f64) {
    v.sort_by(|a, b| a.partial_cmp(b).unwrap());
    let at = |q: f64| v[((q * (v.len() - 1) as f64).round() as usize).min(v.len() - 1)];
    (at(0.5), at(0.95))
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn the_viewer_in_a_real_browser() {
    let started = Instant::now();
    let out = artefacts();
    std::fs::create_dir_all(&out).unwrap();
    // First, so a machine without Chromium fails at once, saying how to install it.
    let browser = Browser::start().await.unwrap();
    let dir = tempfile::tempdir().unwrap();
    let data = dir.path().join("data");
    let demo = start_demo(&data);
    let demo_ready = started.elapsed();
    let base = demo.base.clone();
    let shot = |name: &str| out.join(format!("{name}.png"));

    // 1. The page is the server's own, and it asks for a token.
    browser.goto(&format!("{base}/")).await.unwrap();
    browser
        .wait_for("document.querySelector('#login #token')", WAIT)
        .await
        .unwrap();
    browser.screenshot(&shot("01-login")).await.unwrap();
    // A wrong token is refused by the server, and the page says so.
    browser.type_into("#token", "hz_not-a-token").await.unwrap();
    browser.click("#login button[type=submit]").await.unwrap();
    browser
        .wait_for(
            "document.querySelector('#login .error')?.textContent.includes('not accepted')",
            WAIT,
        )
        .await
        .unwrap();
    // The demo's reader token, pasted.
    browser.type_into("#token", &demo.reader).await.unwrap();
    browser.click("#login button[type=submit]").await.unwrap();

    // 2. The demo's sessions, with state and rows.
    let sessions = browser
        .wait_for(
            "window.hz.sessions && window.hz.sessions.length >= 3 && window.hz.sessions",
            WAIT,
        )
        .await
        .unwrap();
    for id in [
        "demo-usaf-hadamard",
        "demo-double-slit-dgi",
        "demo-lambert-camera",
    ] {
        assert!(
            sessions.as_array().unwrap().contains(&json!(id)),
            "{sessions}"
        );
    }
    let row_text = browser
        .execute(
            "return document.querySelector('tr[data-session=\"demo-usaf-hadamard\"]').innerText",
            json!([]),
        )
        .await
        .unwrap();
    let digits: String = row_text
        .as_str()
        .unwrap()
        .chars()
        .filter(|c| c.is_ascii_digit() || *c == '/')
        .collect();
    assert!(digits.contains("8192/8192"), "{row_text}");
    browser.screenshot(&shot("02-sessions")).await.unwrap();
    // The token is in the tab's session storage, not in the address.
    let where_ = browser
        .execute(
            "return [location.href, sessionStorage.getItem('helmholtz.token')]",
            json!([]),
        )
        .await
        .unwrap();
    assert!(!where_[0].as_str().unwrap().contains("hz_"), "{where_}");
    assert_eq!(where_[1], json!(demo.reader));

    // The demo's link opens the viewer ready to use, and the token leaves the address bar.
    browser.click("#logout").await.unwrap();
    browser
        .wait_for("document.querySelector('#login #token')", WAIT)
        .await
        .unwrap();
    browser.goto("about:blank").await.unwrap();
    browser.goto(&demo.viewer_link).await.unwrap();
    browser
        .wait_for("window.hz.sessions && window.hz.sessions.length >= 3", WAIT)
        .await
        .unwrap();
    let href = browser
        .execute("return location.href", json!([]))
        .await
        .unwrap();
    assert!(!href.as_str().unwrap().contains("token"), "{href}");

    // 3. A dual image: the report's figures, the plot, the image drawn, zoomed, side by side
    // with a second reconstruction of the same session (requested here over REST).
    let client = helmholtz_tests::http_client();
    let second: Value = client
        .post(format!(
            "{base}/v1/sessions/demo-usaf-hadamard/reconstructions"
        ))
        .bearer_auth(&demo.reader)
        .json(&json!({"method": "dgi"}))
        .send()
        .await
        .unwrap()
        .json()
        .await
        .unwrap();
    let second_id = second["id"].as_i64().unwrap();
    wait_done(&client, &base, &demo.reader, second_id).await;
    browser
        .click("tr[data-session=\"demo-usaf-hadamard\"] a")
        .await
        .unwrap();
    browser
        .wait_for("window.hz.dual && window.hz.dual.draws >= 1", WAIT)
        .await
        .unwrap();
    let recon_row = browser
        .execute(
            "return [...document.querySelectorAll('#reconstructions tbody tr')].find(r => r.children[1].textContent === 'direct').innerText",
            json!([]),
        )
        .await
        .unwrap();
    assert!(
        recon_row.as_str().unwrap().contains("direct"),
        "{recon_row}"
    );
    // PSNR against the known truth is shown (the demo's Hadamard inverse: > 30 dB).
    let psnr: f64 = browser
        .execute(
            "return [...document.querySelectorAll('#reconstructions tbody tr')].find(r => r.children[1].textContent === 'direct').children[7].textContent",
            json!([]),
        )
        .await
        .unwrap()
        .as_str()
        .unwrap()
        .parse()
        .unwrap();
    assert!(psnr > 30.0, "{psnr}");
    // The speed-against-error plot has a point for each finished reconstruction with an error
    // (the DGI requested above among them).
    let plotted = browser
        .execute(
            "return [...new Set([...document.querySelectorAll('#speed-error g.point')].map(g => Number(g.dataset.reconstruction)))]",
            json!([]),
        )
        .await
        .unwrap();
    let plotted: Vec<i64> = serde_json::from_value(plotted).unwrap();
    assert!(
        plotted.len() >= 2 && plotted.contains(&second_id),
        "plotted {plotted:?}, dgi {second_id}"
    );
    let first_hash = browser
        .execute(
            "return document.querySelector('.imageview canvas').dataset.hash",
            json!([]),
        )
        .await
        .unwrap();
    assert!(first_hash.is_string(), "{first_hash}");
    // Zoom in (button), then pan (a drag on the image): the pixels on screen change each time.
    let screen = "return document.querySelector('.imageview canvas').toDataURL()";
    let fitted = browser.execute(screen, json!([])).await.unwrap();
    browser
        .click(".imageview .zoomtools button[aria-label='Zoom in']")
        .await
        .unwrap();
    let zoomed = browser.execute(screen, json!([])).await.unwrap();
    assert_ne!(fitted, zoomed, "zoom in redraws the image larger");
    browser
        .execute(
            "document.querySelector('.imageview canvas').scrollIntoView({block: 'center'})",
            json!([]),
        )
        .await
        .unwrap();
    browser
        .drag(".imageview canvas", (0, 0), (60, 40))
        .await
        .unwrap();
    let panned = browser.execute(screen, json!([])).await.unwrap();
    assert_ne!(zoomed, panned, "a drag pans the image");
    // Linear display: the same image, drawn again with another scale.
    let draws = browser
        .execute("return window.hz.dual.draws", json!([]))
        .await
        .unwrap();
    browser
        .execute(
            "const s = document.querySelector('#image-mode'); s.value = 'linear'; s.dispatchEvent(new Event('change'));",
            json!([]),
        )
        .await
        .unwrap();
    browser
        .wait_for(
            &format!("window.hz.dual.draws > {draws} && document.querySelector('.imageview figcaption').textContent.includes('linear display')"),
            WAIT,
        )
        .await
        .unwrap();
    // Side by side with the second reconstruction: two different images.
    browser
        .execute(
            "const pick = document.querySelector('#image-recon').value; const s = document.querySelector('#image-compare'); s.value = [...s.options].map(o => o.value).find(v => v && v !== pick); s.dispatchEvent(new Event('change'));",
            json!([]),
        )
        .await
        .unwrap();
    let pair = browser
        .wait_for(
            "(() => { const c = document.querySelectorAll('.pair')[0].querySelectorAll('canvas'); return c[1].dataset.hash && !c[1].closest('figure').hidden && [c[0].dataset.hash, c[1].dataset.hash]; })()",
            WAIT,
        )
        .await
        .unwrap();
    assert_ne!(pair[0], pair[1], "two reconstructions side by side");
    browser.screenshot(&shot("03-dual-image")).await.unwrap();
    // A detector's weight: the relit image changes.
    browser
        .wait_for(
            "window.hz.relight && window.hz.relight.drawn >= 1 && window.hz.relight.answered === window.hz.relight.wanted",
            WAIT,
        )
        .await
        .unwrap();
    let unweighted = browser
        .execute("return window.hz.relight.hashes.at(-1)", json!([]))
        .await
        .unwrap();
    browser
        .execute(
            "const s = document.querySelector('input[data-channel]'); s.value = '0.25'; s.dispatchEvent(new Event('input'));",
            json!([]),
        )
        .await
        .unwrap();
    browser
        .wait_for(
            "window.hz.relight.drawn >= 2 && window.hz.relight.answered === window.hz.relight.wanted && !window.hz.relight.inFlight",
            WAIT,
        )
        .await
        .unwrap();
    let weighted = browser
        .execute("return window.hz.relight.hashes.at(-1)", json!([]))
        .await
        .unwrap();
    assert_ne!(unweighted, weighted, "the detector's weight relights");

    // 4. Relighting the camera session: drag a disc light on the camera's view.
    browser
        .goto(&format!("{base}/#/sessions/demo-lambert-camera"))
        .await
        .unwrap();
    browser
        .wait_for(
            "document.querySelector('#camera-view')?.dataset.ready === '1' && window.hz.relight && window.hz.relight.drawn >= 1 && !window.hz.relight.inFlight",
            WAIT,
        )
        .await
        .unwrap();
    browser
        .execute(
            "document.querySelector('#camera-view').scrollIntoView({block: 'center'})",
            json!([]),
        )
        .await
        .unwrap();
    let lit_all = browser
        .execute("return window.hz.relight.hashes.at(-1)", json!([]))
        .await
        .unwrap();
    browser
        .drag("#camera-view", (-120, -60), (-60, -30))
        .await
        .unwrap();
    let settled =
        "window.hz.relight.answered === window.hz.relight.wanted && !window.hz.relight.inFlight";
    browser.wait_for(settled, WAIT).await.unwrap();
    let lit_disc = browser
        .execute("return window.hz.relight.hashes.at(-1)", json!([]))
        .await
        .unwrap();
    assert_ne!(lit_all, lit_disc, "the relit image changed with the light");
    browser.screenshot(&shot("04-relight")).await.unwrap();
    // Every control on the page has a label (its own <label> or an aria-label).
    let unlabelled = browser
        .execute(
            "return [...document.querySelectorAll('input, select, textarea')].filter(e => !(e.labels && e.labels.length) && !e.getAttribute('aria-label')).map(e => e.outerHTML)",
            json!([]),
        )
        .await
        .unwrap();
    assert_eq!(unlabelled, json!([]), "controls without a label");

    // 100 drags along a path. Each presses (and waits for the image of the press), moves and
    // waits for the image of the move, then releases: the move's image is timed in the browser
    // from the pointermove event to the relit image drawn on the canvas, with no earlier request
    // in front of it.
    let before = browser
        .execute("return window.hz.relight.timings.length", json!([]))
        .await
        .unwrap()
        .as_u64()
        .unwrap() as usize;
    for i in 0..100i64 {
        let a = (i as f64) * 0.37;
        let (x, y) = ((a.cos() * 110.0) as i64, (a.sin() * 80.0) as i64);
        browser
            .pointer("#camera-view", &[("move", x, y), ("down", 0, 0)])
            .await
            .unwrap();
        browser.wait_for(settled, WAIT).await.unwrap();
        browser
            .pointer(
                "#camera-view",
                &[("move", x + 9 - (i % 5) * 4, y + 5 - (i % 3) * 5)],
            )
            .await
            .unwrap();
        browser.wait_for(settled, WAIT).await.unwrap();
        browser
            .pointer("#camera-view", &[("up", 0, 0)])
            .await
            .unwrap();
        browser.release().await.unwrap();
    }
    let stats = browser
        .execute("return window.hz.relight", json!([]))
        .await
        .unwrap();
    assert_eq!(stats["errors"], 0, "{}", stats["lastError"]);
    let timings = stats["timings"].as_array().unwrap()[before..].to_vec();
    let moves: Vec<f64> = timings
        .iter()
        .filter(|t| t["kind"] == "pointermove")
        .map(|t| t["ms"].as_f64().unwrap())
        .collect();
    assert_eq!(
        moves.len(),
        100,
        "one relit image drawn per drag's move ({} images in all)",
        timings.len()
    );
    let hashes: std::collections::BTreeSet<String> = stats["hashes"].as_array().unwrap()[before..]
        .iter()
        .map(|h| h.as_str().unwrap().to_string())
        .collect();
    assert!(
        hashes.len() >= 50,
        "the relit images change as the light moves: {} distinct of {}",
        hashes.len(),
        timings.len()
    );
    let (median, p95) = median_p95(moves.clone());
    let part = |key: &str| -> Value {
        let v: Vec<f64> = timings
            .iter()
            .filter(|t| t["kind"] == "pointermove")
            .map(|t| t[key].as_f64().unwrap())
            .collect();
        let (m, p) = median_p95(v);
        json!({"median": m, "p95": p})
    };
    let server_compute = {
        let v: Vec<f64> = timings
            .iter()
            .filter(|t| t["kind"] == "pointermove")
            .filter_map(|t| {
                let st = t["serverTiming"].as_str()?;
                st.split("dur=")
                    .nth(1)?
                    .split([',', ';'])
                    .next()?
                    .trim()
                    .parse()
                    .ok()
            })
            .collect();
        if v.is_empty() {
            Value::Null
        } else {
            let n = v.len();
            let (m, p) = median_p95(v);
            json!({"median": m, "p95": p, "answers": n})
        }
    };
    let figures = json!({
        "drags": 100,
        "images_drawn": timings.len(),
        "distinct_images": hashes.len(),
        "move_to_drawn_ms": {"median": median, "p95": p95, "min": moves.iter().cloned().fold(f64::INFINITY, f64::min), "max": moves.iter().cloned().fold(0.0, f64::max)},
        "parts_ms": {
            "event_to_handler": part("toHandler"),
            "request_to_response": part("network"),
            "decode_and_draw": part("draw"),
            "server_compute": server_compute,
        },
        "session": "demo-lambert-camera (32x32 projector, 32x24 camera)",
        "backend": format!("{:?}", backend()),
    });
    std::fs::write(
        out.join("relight-latency.json"),
        serde_json::to_string_pretty(&figures).unwrap(),
    )
    .unwrap();
    println!(
        "relight latency over 100 drags (move -> relit image drawn): median {median:.1} ms, p95 {p95:.1} ms\n{}",
        serde_json::to_string_pretty(&figures).unwrap()
    );

    // The stripe and brush tools relight too.
    for tool in ["stripe", "brush"] {
        let last = browser
            .execute("return window.hz.relight.hashes.at(-1)", json!([]))
            .await
            .unwrap();
        browser
            .execute(
                &format!("const s = document.querySelector('#relight-tool'); s.value = '{tool}'; s.dispatchEvent(new Event('change'));"),
                json!([]),
            )
            .await
            .unwrap();
        browser
            .drag("#camera-view", (-100, -40), (30, 20))
            .await
            .unwrap();
        browser.wait_for(settled, WAIT).await.unwrap();
        let now = browser
            .execute("return window.hz.relight.hashes.at(-1)", json!([]))
            .await
            .unwrap();
        assert_ne!(last, now, "{tool} relights");
    }
    // A light from an image file (any size; the page resizes it to the camera): the left half
    // of the camera lit.
    let light_png = dir.path().join("light.png");
    {
        let (w, h) = (64u32, 48u32);
        let mut encoder = png::Encoder::new(std::fs::File::create(&light_png).unwrap(), w, h);
        encoder.set_color(png::ColorType::Grayscale);
        encoder.set_depth(png::BitDepth::Eight);
        let pixels: Vec<u8> = (0..w * h)
            .map(|i| if i % w < w / 2 { 255 } else { 0 })
            .collect();
        let mut writer = encoder.write_header().unwrap();
        writer.write_image_data(&pixels).unwrap();
    }
    let last = browser
        .execute("return window.hz.relight.hashes.at(-1)", json!([]))
        .await
        .unwrap();
    let drawn = browser
        .execute("return window.hz.relight.drawn", json!([]))
        .await
        .unwrap();
    browser
        .type_into("#relight-file", light_png.to_str().unwrap())
        .await
        .unwrap();
    browser
        .wait_for(
            &format!("window.hz.relight.drawn > {drawn} && {settled}"),
            WAIT,
        )
        .await
        .unwrap();
    let now = browser
        .execute("return window.hz.relight.hashes.at(-1)", json!([]))
        .await
        .unwrap();
    assert_ne!(last, now, "a light from an image relights");
    let errors = browser
        .execute("return window.hz.relight.errors", json!([]))
        .await
        .unwrap();
    assert_eq!(errors, 0);

    // The primal prediction of a stored pattern beside its measured frame, with the error.
    browser.click("#primal-go").await.unwrap();
    let primal = browser
        .wait_for(
            "document.querySelector('#primal-error')?.textContent.includes('relative error') && document.querySelector('#primal-measured')?.dataset.hash && document.querySelector('#primal-error').textContent",
            WAIT,
        )
        .await
        .unwrap();
    assert!(primal.as_str().unwrap().contains("PSNR"), "{primal}");
    browser.screenshot(&shot("05-primal")).await.unwrap();

    // 5. A reconstruction job from the generated form: progress streams in; cancel it.
    browser
        .goto(&format!("{base}/#/sessions/demo-double-slit-dgi"))
        .await
        .unwrap();
    browser
        .wait_for(
            "document.querySelector('#job-method option[value=tv]')",
            WAIT,
        )
        .await
        .unwrap();
    // The methods are the server's own (the OpenAPI document's enum).
    let methods = browser
        .execute(
            "return [...document.querySelectorAll('#job-method option')].map(o => o.value)",
            json!([]),
        )
        .await
        .unwrap();
    for m in ["gi", "dgi", "auto", "tv"] {
        assert!(methods.as_array().unwrap().contains(&json!(m)), "{methods}");
    }
    browser
        .execute(
            "const s = document.querySelector('#job-method'); s.value = 'tv'; s.dispatchEvent(new Event('change')); document.querySelector('#job-params').value = '';",
            json!([]),
        )
        .await
        .unwrap();
    browser
        .type_into("#job-params", r#"{"max_iter": 100000}"#)
        .await
        .unwrap();
    browser.click("#job-submit").await.unwrap();
    let job: i64 = browser
        .wait_for("document.querySelector('#jobs li')?.dataset.job", WAIT)
        .await
        .unwrap()
        .as_str()
        .unwrap()
        .parse()
        .unwrap();
    // Live: the stream's events arrive (the first at once, then as the state moves on).
    browser
        .wait_for(
            "document.querySelector('#jobs li [data-state=running]')",
            WAIT,
        )
        .await
        .unwrap();
    browser.screenshot(&shot("06-job-running")).await.unwrap();
    browser.click("#jobs li button.cancel").await.unwrap();
    browser
        .wait_for(
            "document.querySelector('#jobs li [data-state=cancelled]')",
            WAIT,
        )
        .await
        .unwrap();
    let events: u64 = browser
        .execute(
            "return Number(document.querySelector('#jobs li').dataset.events)",
            json!([]),
        )
        .await
        .unwrap()
        .as_u64()
        .unwrap();
    assert!(events >= 2, "the job's state streamed in: {events} events");
    browser.screenshot(&shot("07-job-cancelled")).await.unwrap();
    let view: Value = client
        .get(format!("{base}/v1/reconstructions/{job}"))
        .bearer_auth(&demo.reader)
        .send()
        .await
        .unwrap()
        .json()
        .await
        .unwrap();
    assert_eq!(view["state"], "cancelled", "{view}");
    assert_eq!(view["method"], "tv", "{view}");

    // 6. Another lab's session: not listed, and its page refused like a missing one.
    let other = create_token_on(
        backend(),
        &binary("helmholtz-server"),
        &data,
        "other-lab",
        "rig,reader",
    )
    .unwrap();
    let r = client
        .post(format!("{base}/v1/sessions"))
        .bearer_auth(&other)
        .json(&json!({
            "id": "other-lab-session",
            "rig": "theirs",
            "patterns": {"family": "bernoulli", "width": 32, "height": 32, "count": 64, "seed": 1, "fill": 0.5},
            "channels": ["d"],
        }))
        .send()
        .await
        .unwrap();
    assert_eq!(r.status(), 201, "{}", r.text().await.unwrap());
    browser
        .execute("window.hz.sessions = null", json!([]))
        .await
        .unwrap();
    browser.goto(&format!("{base}/#/")).await.unwrap();
    let listed = browser
        .wait_for("window.hz.sessions && document.querySelector('#sessions tbody tr') && window.hz.sessions", WAIT)
        .await
        .unwrap();
    assert!(
        !listed
            .as_array()
            .unwrap()
            .contains(&json!("other-lab-session")),
        "{listed}"
    );
    browser
        .goto(&format!("{base}/#/sessions/other-lab-session"))
        .await
        .unwrap();
    let refused = browser
        .wait_for("document.querySelector('#page-error')?.textContent", WAIT)
        .await
        .unwrap();
    assert!(refused.as_str().unwrap().contains("not found"), "{refused}");
    browser
        .screenshot(&shot("08-other-lab-refused"))
        .await
        .unwrap();

    // 7. Live upload progress: rows arriving in a new session of the demo's lab show up in the
    // open list without a reload.
    let put_rows = |start: u64, rows: u64| {
        let values: Vec<u8> = (start..start + rows)
            .flat_map(|i| (1.0 + i as f64 / 64.0).to_le_bytes())
            .collect();
        client
            .put(format!(
                "{base}/v1/sessions/viewer-upload/rows?start_row={start}"
            ))
            .bearer_auth(&demo.rig)
            .header("content-type", "application/octet-stream")
            .header(
                "x-helmholtz-crc32c",
                format!("{:08x}", crc32c::crc32c(&values)),
            )
            .body(values)
            .send()
    };
    let r = client
        .post(format!("{base}/v1/sessions"))
        .bearer_auth(&demo.rig)
        .json(&json!({
            "id": "viewer-upload",
            "rig": "browser-test",
            "patterns": {"family": "bernoulli", "width": 8, "height": 8, "count": 64, "seed": 3, "fill": 0.5},
            "channels": ["d"],
        }))
        .send()
        .await
        .unwrap();
    assert_eq!(r.status(), 201, "{}", r.text().await.unwrap());
    let r = put_rows(0, 24).await.unwrap();
    assert!(r.status().is_success(), "{}", r.text().await.unwrap());
    // The open session's page shows its live preview, redrawn as more rows arrive.
    browser
        .goto(&format!("{base}/#/sessions/viewer-upload"))
        .await
        .unwrap();
    let first = browser
        .wait_for(
            "window.hz.preview && window.hz.preview.session === 'viewer-upload' && window.hz.preview.rows === 24 && window.hz.preview",
            WAIT,
        )
        .await
        .unwrap();
    assert_eq!(first["final"], false, "{first}");
    let r = put_rows(24, 16).await.unwrap();
    assert!(r.status().is_success(), "{}", r.text().await.unwrap());
    let second = browser
        .wait_for("window.hz.preview.rows === 40 && window.hz.preview", WAIT)
        .await
        .unwrap();
    assert_ne!(
        first["hash"], second["hash"],
        "the preview was redrawn: {second}"
    );
    let status = browser
        .execute(
            "return document.querySelector('#preview-status').textContent",
            json!([]),
        )
        .await
        .unwrap();
    assert!(
        status.as_str().unwrap().contains("dgi of 40 of 64 rows"),
        "{status}"
    );
    browser.screenshot(&shot("09-live-preview")).await.unwrap();
    browser
        .execute("window.hz.sessions = null", json!([]))
        .await
        .unwrap();
    browser.goto(&format!("{base}/#/")).await.unwrap();
    let progress = |rows: u64| {
        format!(
            "document.querySelector('tr[data-session=\"viewer-upload\"] progress')?.value === {rows}"
        )
    };
    browser.wait_for(&progress(40), WAIT).await.unwrap();
    let r = put_rows(40, 24).await.unwrap();
    assert!(r.status().is_success(), "{}", r.text().await.unwrap());
    browser.wait_for(&progress(64), WAIT).await.unwrap();
    let text = browser
        .execute(
            "return document.querySelector('tr[data-session=\"viewer-upload\"]').innerText",
            json!([]),
        )
        .await
        .unwrap();
    let digits: String = text
        .as_str()
        .unwrap()
        .chars()
        .filter(|c| c.is_ascii_digit() || *c == '/')
        .collect();
    assert!(digits.contains("64/64"), "{text}");
    browser
        .screenshot(&shot("09-upload-progress"))
        .await
        .unwrap();

    // 8. Colour and photometric stereo: a three-detector session with directions (rows over
    // REST), reconstructed: its colour composite and its normals and albedo.
    let s2 = 0.5f64.sqrt();
    let r = client
        .post(format!("{base}/v1/sessions"))
        .bearer_auth(&demo.rig)
        .json(&json!({
            "id": "viewer-rgb",
            "rig": "browser-test",
            "patterns": {"family": "bernoulli", "width": 8, "height": 8, "count": 64, "seed": 5, "fill": 0.5},
            "channels": ["r", "g", "b"],
            "directions": [[s2, 0.0, s2], [-s2, 0.0, s2], [0.0, s2, s2]],
        }))
        .send()
        .await
        .unwrap();
    assert_eq!(r.status(), 201, "{}", r.text().await.unwrap());
    let values: Vec<u8> = (0..64u64 * 3)
        .flat_map(|i| (1.0 + ((i * 2654435761) % 1000) as f64 / 1000.0).to_le_bytes())
        .collect();
    let r = client
        .put(format!("{base}/v1/sessions/viewer-rgb/rows?start_row=0"))
        .bearer_auth(&demo.rig)
        .header("content-type", "application/octet-stream")
        .header(
            "x-helmholtz-crc32c",
            format!("{:08x}", crc32c::crc32c(&values)),
        )
        .body(values)
        .send()
        .await
        .unwrap();
    assert!(r.status().is_success(), "{}", r.text().await.unwrap());
    let rgb: Value = client
        .post(format!("{base}/v1/sessions/viewer-rgb/reconstructions"))
        .bearer_auth(&demo.reader)
        .json(&json!({"method": "dgi"}))
        .send()
        .await
        .unwrap()
        .json()
        .await
        .unwrap();
    wait_done(&client, &base, &demo.reader, rgb["id"].as_i64().unwrap()).await;
    browser
        .goto(&format!("{base}/#/sessions/viewer-rgb"))
        .await
        .unwrap();
    browser
        .wait_for(
            "[...document.querySelectorAll('#photometric-panel img')].filter(i => i.complete && i.naturalWidth === 8).length === 2 && window.hz.dual && window.hz.dual.draws >= 1",
            WAIT,
        )
        .await
        .unwrap();
    let grey = browser
        .execute("return window.hz.dual.draws", json!([]))
        .await
        .unwrap();
    browser
        .execute(
            "const s = document.querySelector('#image-channel'); s.value = '__composite'; s.dispatchEvent(new Event('change'));",
            json!([]),
        )
        .await
        .unwrap();
    browser
        .wait_for(
            &format!("window.hz.dual.draws > {grey} && document.querySelector('.imageview figcaption').textContent.includes('composite')"),
            WAIT,
        )
        .await
        .unwrap();
    browser
        .screenshot(&shot("10-colour-photometric"))
        .await
        .unwrap();
    // Downloads (fetched with the token, saved by the browser): each is the server's own file,
    // the PNG at the display's scale.
    let mode = browser
        .execute(
            "return document.querySelector('#image-mode').value;",
            json!([]),
        )
        .await
        .unwrap();
    let scale = if mode == json!("linear") {
        "minmax"
    } else {
        "percentile"
    };
    for (ext, query) in [
        ("npy", "channel=r".to_string()),
        ("png", format!("channel=r&scale={scale}")),
        ("tiff", "channel=r".to_string()),
    ] {
        browser.click(&format!("#download-{ext}")).await.unwrap();
        let saved = browser
            .downloads()
            .join(format!("dual-{}-r.{ext}", rgb["id"]));
        let deadline = Instant::now() + WAIT;
        while !saved.exists() {
            assert!(
                Instant::now() < deadline,
                "no download at {}",
                saved.display()
            );
            tokio::time::sleep(Duration::from_millis(50)).await;
        }
        let served = client
            .get(format!(
                "{base}/v1/reconstructions/{}/dual.{ext}?{query}",
                rgb["id"]
            ))
            .bearer_auth(&demo.reader)
            .send()
            .await
            .unwrap()
            .bytes()
            .await
            .unwrap();
        assert!(served.len() > 64, "dual.{ext}: {} bytes", served.len());
        let deadline = Instant::now() + WAIT;
        while std::fs::read(&saved).unwrap() != served {
            assert!(
                Instant::now() < deadline,
                "the download differs from dual.{ext}"
            );
            tokio::time::sleep(Duration::from_millis(50)).await;
        }
    }

    // 9. A phone-sized window: the camera session's page reflows without sideways scrolling.
    browser.set_window(400, 900).await.unwrap();
    browser
        .goto(&format!("{base}/#/sessions/demo-lambert-camera"))
        .await
        .unwrap();
    browser
        .wait_for(
            "document.querySelector('#camera-view')?.dataset.ready === '1' && document.querySelector('#jobs-panel')",
            WAIT,
        )
        .await
        .unwrap();
    let overflow = browser
        .execute(
            "return [document.documentElement.scrollWidth, window.innerWidth]",
            json!([]),
        )
        .await
        .unwrap();
    assert!(
        overflow[0].as_i64().unwrap() <= overflow[1].as_i64().unwrap(),
        "page wider than the window: {overflow}"
    );
    browser.screenshot(&shot("11-narrow")).await.unwrap();

    // Every request the page made went to the server under test.
    let hosts = browser
        .execute(
            "return performance.getEntriesByType('resource').map(e => new URL(e.name).origin)",
            json!([]),
        )
        .await
        .unwrap();
    for origin in hosts.as_array().unwrap() {
        assert_eq!(origin.as_str().unwrap(), base, "{hosts}");
    }
    browser.quit().await;
    println!(
        "browser test: demo ready in {:.1} s, whole test {:.1} s; screenshots in {}",
        demo_ready.as_secs_f64(),
        started.elapsed().as_secs_f64(),
        out.display()
    );
}
