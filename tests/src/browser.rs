//! A headless Chromium driven over the W3C WebDriver protocol by Debian's `chromedriver` (the
//! browser vendor's own, maintained driver), for the web viewer's end-to-end tests
//! (`tests/tests/browser.rs`). The protocol is JSON over HTTP, spoken here with the reqwest the
//! harness already links: a few commands (navigate, execute script, find, click, type, pointer
//! actions, screenshot) need no client crate of their own.
//!
//! Chromium runs with `--headless --no-sandbox --disable-gpu --disable-quic --no-first-run
//! --disable-background-networking --disable-component-update --disable-sync`, no proxy, and a
//! fresh profile directory, so it asks nothing of any network but the server under test.
//! Without Chromium or chromedriver [`Browser::start`] fails saying how to install them; set
//! `HELMHOLTZ_CHROMIUM` / `HELMHOLTZ_CHROMEDRIVER` to use other binaries.

use std::io::{BufRead, BufReader, Write};
use std::path::{Path, PathBuf};
use std::process::{Child, Command, Stdio};
use std::time::{Duration, Instant};

use anyhow::{Context, bail};
use serde_json::{Value, json};

/// The W3C name of an element reference in JSON.
const ELEMENT: &str = "element-6066-11e4-a52e-4f735466cecf";

/// The binary `env` names (if that file exists), else the first of `names` on `PATH`.
fn find_binary(env: &str, names: &[&str]) -> Option<PathBuf> {
    locate(std::env::var_os(env), std::env::var_os("PATH"), names)
}

fn locate(
    explicit: Option<std::ffi::OsString>,
    path: Option<std::ffi::OsString>,
    names: &[&str],
) -> Option<PathBuf> {
    if let Some(p) = explicit {
        let p = PathBuf::from(p);
        return p.is_file().then_some(p);
    }
    for dir in std::env::split_paths(&path?) {
        for name in names {
            let p = dir.join(name);
            if p.is_file() {
                return Some(p);
            }
        }
    }
    None
}

/// How to provide what is missing, for the failure of a browser test without it.
const HOW: &str = "install them with `apt-get install -y chromium chromium-driver` (Debian; .ci/run does this), \
                   or point HELMHOLTZ_CHROMIUM and HELMHOLTZ_CHROMEDRIVER at the binaries";

fn missing(what: &str) -> String {
    format!("the browser tests need {what}, and none was found: {HOW}")
}

/// One Chromium behind one chromedriver; both end when dropped.
pub struct Browser {
    driver: Child,
    port: u16,
    session: String,
    http: reqwest::Client,
    _profile: tempfile::TempDir,
    downloads: tempfile::TempDir,
}

impl Browser {
    /// Starts chromedriver on a free port and a headless Chromium session with a fresh profile.
    pub async fn start() -> anyhow::Result<Browser> {
        let how = HOW;
        let chromium = find_binary("HELMHOLTZ_CHROMIUM", &["chromium", "chromium-browser"])
            .with_context(|| missing("Chromium"))?;
        let chromedriver = find_binary("HELMHOLTZ_CHROMEDRIVER", &["chromedriver"])
            .with_context(|| missing("chromedriver"))?;
        let port = {
            let l = std::net::TcpListener::bind("127.0.0.1:0")?;
            l.local_addr()?.port()
        };
        let mut driver = Command::new(&chromedriver)
            .arg(format!("--port={port}"))
            .stdin(Stdio::null())
            .stdout(Stdio::piped())
            .stderr(Stdio::inherit())
            .spawn()
            .with_context(|| format!("starting {}: {how}", chromedriver.display()))?;
        // Drain its output (it logs a line per start) so it never blocks on a full pipe.
        let out = driver.stdout.take().expect("piped");
        std::thread::spawn(move || for _ in BufReader::new(out).lines() {});
        let http = reqwest::Client::builder()
            .no_proxy()
            .timeout(Duration::from_secs(120))
            .build()?;
        let base = format!("http://127.0.0.1:{port}");
        let deadline = Instant::now() + Duration::from_secs(20);
        loop {
            let ready = async {
                let v: Value = http
                    .get(format!("{base}/status"))
                    .send()
                    .await?
                    .json()
                    .await?;
                anyhow::Ok(v["value"]["ready"] == true)
            };
            if ready.await.unwrap_or(false) {
                break;
            }
            if let Some(status) = driver.try_wait()? {
                bail!("chromedriver exited with {status}");
            }
            if Instant::now() > deadline {
                let _ = driver.kill();
                bail!("chromedriver did not become ready within 20 s");
            }
            tokio::time::sleep(Duration::from_millis(50)).await;
        }
        let profile = tempfile::tempdir()?;
        let downloads = tempfile::tempdir()?;
        let args = [
            "--headless",
            "--no-sandbox",
            "--disable-gpu",
            "--disable-quic",
            "--no-first-run",
            "--disable-background-networking",
            "--disable-component-update",
            "--disable-sync",
            "--disable-dev-shm-usage",
            "--no-proxy-server",
            "--window-size=1280,1600",
        ]
        .iter()
        .map(|s| s.to_string())
        .chain([format!("--user-data-dir={}", profile.path().display())])
        .collect::<Vec<_>>();
        let capabilities = json!({"capabilities": {"alwaysMatch": {
            "browserName": "chrome",
            "goog:chromeOptions": {"binary": chromium, "args": args, "prefs": {
                "download.default_directory": downloads.path(),
                "download.prompt_for_download": false,
            }},
            "timeouts": {"script": 60000, "pageLoad": 60000, "implicit": 0},
        }}});
        let r: Value = http
            .post(format!("{base}/session"))
            .json(&capabilities)
            .send()
            .await?
            .json()
            .await?;
        let Some(session) = r["value"]["sessionId"].as_str() else {
            let _ = driver.kill();
            bail!(
                "chromedriver could not start {}: {}",
                chromium.display(),
                r["value"]
            );
        };
        Ok(Browser {
            driver,
            port,
            session: session.to_string(),
            http,
            _profile: profile,
            downloads,
        })
    }

    async fn command(
        &self,
        method: &str,
        path: &str,
        body: Option<Value>,
    ) -> anyhow::Result<Value> {
        let url = format!(
            "http://127.0.0.1:{}/session/{}{path}",
            self.port, self.session
        );
        let mut r = self.http.request(method.parse()?, &url);
        if let Some(b) = body {
            r = r.json(&b);
        }
        let v: Value = r.send().await?.json().await?;
        let value = v["value"].clone();
        if let Some(error) = value.get("error").and_then(Value::as_str) {
            bail!(
                "WebDriver {method} {path}: {error}: {}",
                value["message"].as_str().unwrap_or("")
            );
        }
        Ok(value)
    }

    pub async fn goto(&self, url: &str) -> anyhow::Result<()> {
        self.command("POST", "/url", Some(json!({ "url": url })))
            .await
            .map(drop)
    }

    /// Runs `script` (a function body; `arguments` holds `args`) and returns its value.
    pub async fn execute(&self, script: &str, args: Value) -> anyhow::Result<Value> {
        self.command(
            "POST",
            "/execute/sync",
            Some(json!({"script": script, "args": args})),
        )
        .await
    }

    /// Runs `script` whose last argument is a callback to call with the result.
    pub async fn execute_async(&self, script: &str, args: Value) -> anyhow::Result<Value> {
        self.command(
            "POST",
            "/execute/async",
            Some(json!({"script": script, "args": args})),
        )
        .await
    }

    /// Polls the JavaScript expression `expr` until it is truthy; returns its value.
    pub async fn wait_for(&self, expr: &str, timeout: Duration) -> anyhow::Result<Value> {
        let deadline = Instant::now() + timeout;
        let script = format!("try {{ return ({expr}); }} catch (e) {{ return null; }}");
        loop {
            let v = self.execute(&script, json!([])).await?;
            let truthy = match &v {
                Value::Null => false,
                Value::Bool(b) => *b,
                Value::Number(n) => n.as_f64() != Some(0.0),
                Value::String(s) => !s.is_empty(),
                _ => true,
            };
            if truthy {
                return Ok(v);
            }
            if Instant::now() > deadline {
                let status = self
                    .execute(
                        "return (document.getElementById('status')||{}).textContent + ' | ' + (document.getElementById('main')||{}).innerText",
                        json!([]),
                    )
                    .await
                    .unwrap_or_default();
                bail!("waited {timeout:?} for `{expr}`; the page says: {status}");
            }
            tokio::time::sleep(Duration::from_millis(25)).await;
        }
    }

    /// The element matching `css` (an error if none).
    pub async fn find(&self, css: &str) -> anyhow::Result<Value> {
        let v = self
            .command(
                "POST",
                "/element",
                Some(json!({"using": "css selector", "value": css})),
            )
            .await
            .with_context(|| format!("no element {css:?}"))?;
        Ok(v)
    }

    fn element_id(element: &Value) -> anyhow::Result<String> {
        element[ELEMENT]
            .as_str()
            .map(str::to_string)
            .context("not an element reference")
    }

    /// Clicks the element matching `css` (a real pointer click, scrolled into view).
    pub async fn click(&self, css: &str) -> anyhow::Result<()> {
        let id = Self::element_id(&self.find(css).await?)?;
        self.command("POST", &format!("/element/{id}/click"), Some(json!({})))
            .await
            .map(drop)
    }

    /// Types `text` into the element matching `css` (real key events).
    pub async fn type_into(&self, css: &str, text: &str) -> anyhow::Result<()> {
        let id = Self::element_id(&self.find(css).await?)?;
        self.command(
            "POST",
            &format!("/element/{id}/value"),
            Some(json!({ "text": text })),
        )
        .await
        .map(drop)
    }

    /// A mouse drag on the element matching `css`: press at `from`, move to `to`, release
    /// (offsets in CSS pixels from the element's centre), as real input events.
    pub async fn drag(&self, css: &str, from: (i64, i64), to: (i64, i64)) -> anyhow::Result<()> {
        let element = self.find(css).await?;
        let origin = json!({ ELEMENT: Self::element_id(&element)? });
        let actions = json!({"actions": [{
            "type": "pointer",
            "id": "mouse",
            "parameters": {"pointerType": "mouse"},
            "actions": [
                {"type": "pointerMove", "duration": 0, "origin": origin, "x": from.0, "y": from.1},
                {"type": "pointerDown", "button": 0},
                {"type": "pointerMove", "duration": 0, "origin": origin, "x": to.0, "y": to.1},
                {"type": "pointerUp", "button": 0},
            ],
        }]});
        self.command("POST", "/actions", Some(actions)).await?;
        self.command("DELETE", "/actions", None).await.map(drop)
    }

    /// Mouse input on the element matching `css`, kept across calls (a button pressed here stays
    /// pressed until [`Browser::release`]): `steps` are `("move", x, y)` (offsets in CSS pixels
    /// from the element's centre), `("down", 0, 0)` or `("up", 0, 0)`.
    pub async fn pointer(&self, css: &str, steps: &[(&str, i64, i64)]) -> anyhow::Result<()> {
        let element = self.find(css).await?;
        let origin = json!({ ELEMENT: Self::element_id(&element)? });
        let actions: Vec<Value> = steps
            .iter()
            .map(|(kind, x, y)| match *kind {
                "move" => {
                    json!({"type": "pointerMove", "duration": 0, "origin": origin, "x": x, "y": y})
                }
                "down" => json!({"type": "pointerDown", "button": 0}),
                _ => json!({"type": "pointerUp", "button": 0}),
            })
            .collect();
        let actions = json!({"actions": [{
            "type": "pointer",
            "id": "mouse",
            "parameters": {"pointerType": "mouse"},
            "actions": actions,
        }]});
        self.command("POST", "/actions", Some(actions))
            .await
            .map(drop)
    }

    /// Releases every pressed button and key.
    pub async fn release(&self) -> anyhow::Result<()> {
        self.command("DELETE", "/actions", None).await.map(drop)
    }

    /// The directory Chromium saves downloads in (empty at the start).
    pub fn downloads(&self) -> &Path {
        self.downloads.path()
    }

    /// Resizes the window to `width` x `height` CSS pixels.
    pub async fn set_window(&self, width: u32, height: u32) -> anyhow::Result<()> {
        self.command(
            "POST",
            "/window/rect",
            Some(json!({"width": width, "height": height})),
        )
        .await
        .map(drop)
    }

    /// Saves a PNG screenshot of the window at `path`.
    pub async fn screenshot(&self, path: &Path) -> anyhow::Result<()> {
        let v = self.command("GET", "/screenshot", None).await?;
        let png = base64_decode(v.as_str().context("screenshot is a string")?)?;
        if let Some(dir) = path.parent() {
            std::fs::create_dir_all(dir)?;
        }
        std::fs::write(path, png)?;
        Ok(())
    }

    /// Ends the session (Chromium exits) and chromedriver.
    pub async fn quit(mut self) {
        let _ = self.command("DELETE", "", None).await;
        self.session.clear();
    }
}

impl Drop for Browser {
    fn drop(&mut self) {
        if !self.session.is_empty() {
            // Ends the session (and with it Chromium) without a runtime: one raw HTTP request.
            if let Ok(mut s) = std::net::TcpStream::connect(("127.0.0.1", self.port)) {
                let _ = s.set_read_timeout(Some(Duration::from_secs(10)));
                let _ = write!(
                    s,
                    "DELETE /session/{} HTTP/1.1\r\nHost: 127.0.0.1\r\nConnection: close\r\n\r\n",
                    self.session
                );
                let _ = std::io::Read::read_to_end(&mut s, &mut Vec::new());
            }
        }
        let _ = self.driver.kill();
        let _ = self.driver.wait();
    }
}

/// Standard base64 (with padding) to bytes.
fn base64_decode(text: &str) -> anyhow::Result<Vec<u8>> {
    let value = |c: u8| -> anyhow::Result<u32> {
        Ok(match c {
            b'A'..=b'Z' => c - b'A',
            b'a'..=b'z' => c - b'a' + 26,
            b'0'..=b'9' => c - b'0' + 52,
            b'+' => 62,
            b'/' => 63,
            _ => bail!("not base64: {:?}", c as char),
        } as u32)
    };
    let bytes: Vec<u8> = text
        .bytes()
        .filter(|c| !c.is_ascii_whitespace() && *c != b'=')
        .collect();
    let mut out = Vec::with_capacity(bytes.len() * 3 / 4);
    for chunk in bytes.chunks(4) {
        let mut n = 0u32;
        for (i, c) in chunk.iter().enumerate() {
            n |= value(*c)? << (18 - 6 * i);
        }
        let take = chunk.len() - 1;
        for i in 0..take {
            out.push((n >> (16 - 8 * i)) as u8);
        }
    }
    Ok(out)
}

#[cfg(test)]
mod tests {
    #[test]
    fn a_missing_browser_is_reported_with_how_to_install_it() {
        let empty = tempfile::tempdir().unwrap();
        let path = Some(empty.path().as_os_str().to_owned());
        assert_eq!(super::locate(None, path.clone(), &["chromium"]), None);
        // An explicit path that does not exist is missing too (not handed to chromedriver).
        let nowhere = Some(empty.path().join("chromium").into_os_string());
        assert_eq!(super::locate(nowhere, path, &["chromium"]), None);
        let found = empty.path().join("chromium");
        std::fs::write(&found, "").unwrap();
        let path = Some(empty.path().as_os_str().to_owned());
        assert_eq!(super::locate(None, path, &["chromium"]), Some(found));
        let message = super::missing("Chromium");
        assert!(
            message.contains("apt-get install -y chromium chromium-driver"),
            "{message}"
        );
    }

    #[test]
    fn base64_decodes() {
        assert_eq!(super::base64_decode("aGVsbG8=").unwrap(), b"hello");
        assert_eq!(super::base64_decode("aGVsbG8hIQ==").unwrap(), b"hello!!");
        assert_eq!(super::base64_decode("YWJj").unwrap(), b"abc");
    }
}
