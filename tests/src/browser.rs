//! A headless Chromium driven over the W3C WebDriver protocol by Debian's `chromedriver` (the
//! browser vendor's own, maintained driver), for the web viewer's end-to-end tests
//! (`tests/tests/e2e/browser.rs`). The protocol client is the fantoccini crate, connected over plain
//! HTTP (hyper-util's `HttpConnector`, no TLS) to the chromedriver started here on a free
//! 127.0.0.1 port; [`Browser`] is the small interface the tests use on top of it.
//!
//! Chromium runs with `--headless --no-sandbox --disable-gpu --disable-quic --no-first-run
//! --disable-background-networking --disable-component-update --disable-sync`, no proxy, and a
//! fresh profile directory, so it asks nothing of any network but the server under test.
//! Without Chromium or chromedriver [`Browser::start`] fails saying how to install them; set
//! `HELMHOLTZ_CHROMIUM` / `HELMHOLTZ_CHROMEDRIVER` to use other binaries.

use std::future::Future;
use std::io::{BufRead, BufReader, Write};
use std::path::{Path, PathBuf};
use std::process::{Child, Command, Stdio};
use std::time::{Duration, Instant};

use anyhow::{Context, bail};
use fantoccini::actions::{InputSource, MOUSE_BUTTON_LEFT, MouseActions, PointerAction};
use fantoccini::elements::Element;
use fantoccini::{Client, ClientBuilder, Locator};
use hyper_util::client::legacy::connect::HttpConnector;
use serde_json::{Value, json};

/// How long one WebDriver command may take before the test fails instead of hanging.
const COMMAND_TIMEOUT: Duration = Duration::from_secs(120);

/// Awaits the WebDriver command `what`, within [`COMMAND_TIMEOUT`].
async fn within<T, E>(what: &str, command: impl Future<Output = Result<T, E>>) -> anyhow::Result<T>
where
    E: std::error::Error + Send + Sync + 'static,
{
    tokio::time::timeout(COMMAND_TIMEOUT, command)
        .await
        .with_context(|| format!("WebDriver {what}: no answer within {COMMAND_TIMEOUT:?}"))?
        .with_context(|| format!("WebDriver {what}"))
}

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
    /// The WebDriver session's id; empty once [`Browser::quit`] ended it.
    session: String,
    client: Client,
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
        // chromedriver serves once it listens: wait for the port to accept connections.
        let deadline = Instant::now() + Duration::from_secs(20);
        while tokio::net::TcpStream::connect(("127.0.0.1", port))
            .await
            .is_err()
        {
            if let Some(status) = driver.try_wait()? {
                bail!("chromedriver exited with {status}");
            }
            if Instant::now() > deadline {
                let _ = driver.kill();
                let _ = driver.wait();
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
        let Value::Object(capabilities) = json!({
            "browserName": "chrome",
            "goog:chromeOptions": {"binary": chromium, "args": args, "prefs": {
                "download.default_directory": downloads.path(),
                "download.prompt_for_download": false,
            }},
            "timeouts": {"script": 60000, "pageLoad": 60000, "implicit": 0},
        }) else {
            unreachable!("a JSON object")
        };
        // Plain HTTP to 127.0.0.1: hyper-util's connector, which consults no proxy settings.
        let connect = ClientBuilder::new(HttpConnector::new())
            .capabilities(capabilities)
            .connect(&format!("http://127.0.0.1:{port}"))
            .await;
        let client = match connect {
            Ok(client) => client,
            Err(e) => {
                let _ = driver.kill();
                let _ = driver.wait();
                bail!("chromedriver could not start {}: {e}", chromium.display());
            }
        };
        let session = client
            .session_creation_response()
            .map(|r| r.session_id().to_string())
            .unwrap_or_default();
        Ok(Browser {
            driver,
            port,
            session,
            client,
            _profile: profile,
            downloads,
        })
    }

    pub async fn goto(&self, url: &str) -> anyhow::Result<()> {
        within("navigate", self.client.goto(url)).await
    }

    /// Runs `script` (a function body; `arguments` holds `args`) and returns its value.
    pub async fn execute(&self, script: &str, args: Value) -> anyhow::Result<Value> {
        within("execute", self.client.execute(script, Self::args(args)?)).await
    }

    /// Runs `script` whose last argument is a callback to call with the result.
    pub async fn execute_async(&self, script: &str, args: Value) -> anyhow::Result<Value> {
        within(
            "execute async",
            self.client.execute_async(script, Self::args(args)?),
        )
        .await
    }

    /// A script's arguments: a JSON array (or null for none).
    fn args(args: Value) -> anyhow::Result<Vec<Value>> {
        match args {
            Value::Array(args) => Ok(args),
            Value::Null => Ok(Vec::new()),
            other => bail!("script arguments are a JSON array, not {other}"),
        }
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

    /// The element matching `css` (an error if none), as fantoccini's handle.
    async fn element(&self, css: &str) -> anyhow::Result<Element> {
        within("find element", self.client.find(Locator::Css(css)))
            .await
            .with_context(|| format!("no element {css:?}"))
    }

    /// The element matching `css` (an error if none), as its W3C JSON reference.
    pub async fn find(&self, css: &str) -> anyhow::Result<Value> {
        Ok(serde_json::to_value(self.element(css).await?)?)
    }

    /// Clicks the element matching `css` (a real pointer click, scrolled into view).
    pub async fn click(&self, css: &str) -> anyhow::Result<()> {
        let element = self.element(css).await?;
        within("click", element.click()).await
    }

    /// Types `text` into the element matching `css` (real key events).
    pub async fn type_into(&self, css: &str, text: &str) -> anyhow::Result<()> {
        let element = self.element(css).await?;
        within("send keys", element.send_keys(text)).await
    }

    /// A pointer move to (`x`, `y`) CSS pixels from the centre of `element`, taking no time.
    fn move_to(element: &Element, (x, y): (i64, i64)) -> PointerAction {
        PointerAction::MoveToElement {
            element: element.clone(),
            duration: Some(Duration::ZERO),
            x: x as f64,
            y: y as f64,
        }
    }

    /// The one mouse of every action sequence here (one id, so its state carries across calls).
    fn mouse() -> MouseActions {
        MouseActions::new("mouse".to_string())
    }

    /// A mouse drag on the element matching `css`: press at `from`, move to `to`, release
    /// (offsets in CSS pixels from the element's centre), as real input events.
    pub async fn drag(&self, css: &str, from: (i64, i64), to: (i64, i64)) -> anyhow::Result<()> {
        let element = self.element(css).await?;
        let actions = Self::mouse()
            .then(Self::move_to(&element, from))
            .then(PointerAction::Down {
                button: MOUSE_BUTTON_LEFT,
            })
            .then(Self::move_to(&element, to))
            .then(PointerAction::Up {
                button: MOUSE_BUTTON_LEFT,
            });
        within("perform actions", self.client.perform_actions(actions)).await?;
        self.release().await
    }

    /// Mouse input on the element matching `css`, kept across calls (a button pressed here stays
    /// pressed until [`Browser::release`]): `steps` are `("move", x, y)` (offsets in CSS pixels
    /// from the element's centre), `("down", 0, 0)` or `("up", 0, 0)`.
    pub async fn pointer(&self, css: &str, steps: &[(&str, i64, i64)]) -> anyhow::Result<()> {
        let element = self.element(css).await?;
        let actions = steps.iter().fold(Self::mouse(), |actions, &(kind, x, y)| {
            actions.then(match kind {
                "move" => Self::move_to(&element, (x, y)),
                "down" => PointerAction::Down {
                    button: MOUSE_BUTTON_LEFT,
                },
                _ => PointerAction::Up {
                    button: MOUSE_BUTTON_LEFT,
                },
            })
        });
        within("perform actions", self.client.perform_actions(actions)).await
    }

    /// Releases every pressed button and key.
    pub async fn release(&self) -> anyhow::Result<()> {
        within("release actions", self.client.release_actions()).await
    }

    /// The directory Chromium saves downloads in (empty at the start).
    pub fn downloads(&self) -> &Path {
        self.downloads.path()
    }

    /// Resizes the window to `width` x `height` CSS pixels.
    pub async fn set_window(&self, width: u32, height: u32) -> anyhow::Result<()> {
        within(
            "set window rect",
            self.client.set_window_size(width, height),
        )
        .await
    }

    /// Saves a PNG screenshot of the window at `path`.
    pub async fn screenshot(&self, path: &Path) -> anyhow::Result<()> {
        let png = within("screenshot", self.client.screenshot()).await?;
        if let Some(dir) = path.parent() {
            std::fs::create_dir_all(dir)?;
        }
        std::fs::write(path, png)?;
        Ok(())
    }

    /// Ends the session (Chromium exits) and chromedriver.
    pub async fn quit(mut self) {
        let _ = within("delete session", self.client.clone().close()).await;
        self.session.clear();
    }
}

impl Drop for Browser {
    fn drop(&mut self) {
        if !self.session.is_empty() {
            // Ends the session (and with it Chromium) before chromedriver is killed. fantoccini
            // would end it only later, from a task of the async runtime this destructor may not
            // be able to wait for: so one raw HTTP request, blocking.
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
}
