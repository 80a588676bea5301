//! The HTTP side: a server on one socket ([`crate::http`]: one request per connection, with
//! limits), answering from a [`ViewScene`].
//!
//! Routes (all GET):
//!
//! | path | answer |
//! |---|---|
//! | `/` | the page (`web/index.html`) |
//! | `/app.js`, `/gsplat.js` | the page's script and the vendored gsplat.js bundle |
//! | `/scene.splat` | the Gaussians as `.splat` rows ([`crate::splat`]) |
//! | `/api/scene` | [`SceneInfo`] as JSON (mode, prompts, score, default threshold, presets, click) |
//! | `/api/select?prompt=NAME&threshold=T` | selected Gaussian ids, u32 little-endian (400 in click-only mode: no text prompts) |
//! | `/api/click?view=V&x=X&y=Y&threshold=T` | the same for a click; header `X-Click`: JSON of the resolved mask and proposal |
//! | `/api/export.ply?prompt=…` or `?view=…&x=…&y=…` (and `threshold`) | that selection's Gaussians as an INRIA 3DGS PLY download |
//!
//! Everything the page loads comes from these routes: nothing is fetched from elsewhere.
//!
//! Every request goes through [`respond`] first:
//! * only `GET` and `HEAD` are answered (405 otherwise, before any body is read);
//! * on a loopback address the `Host` header must name a loopback host (`localhost`,
//!   `127.x.x.x`, `[::1]`; a port, if given, this one) (421 otherwise), so that a page of another site
//!   whose name resolves to 127.0.0.1 (DNS rebinding) cannot read the scene;
//! * answers carry `X-Content-Type-Options: nosniff`, `X-Frame-Options: DENY`, a
//!   `frame-ancestors 'none'` policy and `Referrer-Policy: no-referrer`;
//! * a server-side failure (500) answers a generic text and prints the detail, which names
//!   files on the server, on stderr only.

use std::net::{IpAddr, SocketAddr, TcpListener, TcpStream};
use std::sync::atomic::{AtomicUsize, Ordering};
use std::time::Duration;

use profuse_query::{Click, ClickTarget};

use crate::error::{Result, ViewError};
use crate::http;
use crate::scene::{SceneInfo, ViewScene};

const INDEX_HTML: &str = include_str!("../web/index.html");
const APP_JS: &str = include_str!("../web/app.js");
const GSPLAT_JS: &str = include_str!("../web/vendor/gsplat.js");

/// An answer to one request.
#[derive(Debug, Clone, PartialEq)]
pub struct Answer {
    /// HTTP status.
    pub status: u16,
    /// Content type.
    pub content_type: &'static str,
    /// Body.
    pub body: Vec<u8>,
    /// Extra headers (name, value).
    pub headers: Vec<(&'static str, String)>,
}

impl Answer {
    fn ok(content_type: &'static str, body: Vec<u8>) -> Answer {
        Answer {
            status: 200,
            content_type,
            body,
            headers: Vec::new(),
        }
    }

    fn error(status: u16, message: String) -> Answer {
        Answer {
            status,
            content_type: "text/plain; charset=utf-8",
            body: message.into_bytes(),
            headers: Vec::new(),
        }
    }
}

/// The listening socket. It is bound before the scene is read, so that a taken port is
/// reported at once.
#[derive(Debug)]
pub struct Listener {
    listener: TcpListener,
    addr: SocketAddr,
}

/// Listens on `host:port` (port 0: any free port). A port in use is
/// [`ViewError::PortInUse`].
pub fn listen(host: IpAddr, port: u16) -> Result<Listener> {
    let wanted = SocketAddr::new(host, port);
    let listener = TcpListener::bind(wanted).map_err(|source| match source.kind() {
        std::io::ErrorKind::AddrInUse => ViewError::PortInUse {
            addr: wanted.to_string(),
        },
        _ => ViewError::Bind {
            addr: wanted.to_string(),
            source,
        },
    })?;
    let addr = listener.local_addr().map_err(|source| ViewError::Bind {
        addr: wanted.to_string(),
        source,
    })?;
    Ok(Listener { listener, addr })
}

impl Listener {
    /// The address it listens on.
    pub fn addr(&self) -> SocketAddr {
        self.addr
    }

    /// The page's URL.
    pub fn url(&self) -> String {
        format!("http://{}/", self.addr)
    }

    /// Answers requests about `scene` until the process ends, each connection on its own
    /// thread (at most [`http::MAX_CONNECTIONS`] at once; 503 beyond). A failed accept
    /// (out of file descriptors) or reply is reported on stderr and does not stop the
    /// server.
    pub fn serve(&self, scene: &ViewScene) {
        let open = AtomicUsize::new(0);
        std::thread::scope(|s| loop {
            let mut stream = match self.listener.accept() {
                Ok((stream, _)) => stream,
                Err(e) => {
                    eprintln!("profuse view: accept failed: {e} (retrying)");
                    std::thread::sleep(Duration::from_millis(100));
                    continue;
                }
            };
            let _ = stream.set_read_timeout(Some(http::READ_TIMEOUT));
            let _ = stream.set_write_timeout(Some(http::WRITE_TIMEOUT));
            if open.fetch_add(1, Ordering::SeqCst) >= http::MAX_CONNECTIONS {
                open.fetch_sub(1, Ordering::SeqCst);
                let busy = hardened(Answer::error(503, "too many connections; try again".into()));
                reply(&mut stream, &busy, true);
                continue;
            }
            let (open, addr) = (&open, self.addr);
            s.spawn(move || {
                serve_connection(scene, stream, addr);
                open.fetch_sub(1, Ordering::SeqCst);
            });
        });
    }
}

/// One connection: its request head, the answer, close.
fn serve_connection(scene: &ViewScene, mut stream: TcpStream, addr: SocketAddr) {
    let (answer, with_body) = match http::read_head(&mut stream) {
        Ok(head) => {
            let a = respond(
                scene,
                &head.method,
                head.host.as_deref(),
                &head.target,
                addr,
            );
            (a, head.method != "HEAD")
        }
        Err(http::HeadError::TooLarge) => {
            let over = format!("request head over {} bytes", http::MAX_HEAD_BYTES);
            (hardened(Answer::error(431, over)), true)
        }
        Err(http::HeadError::Malformed) => (
            hardened(Answer::error(400, "not an HTTP/1.x request".into())),
            true,
        ),
        Err(http::HeadError::Gone) => return,
    };
    reply(&mut stream, &answer, with_body);
}

/// Writes `answer` (already [`hardened`]) with its content type and `no-store`.
fn reply(stream: &mut TcpStream, answer: &Answer, with_body: bool) {
    let mut headers: Vec<(&str, String)> = vec![
        ("Content-Type", answer.content_type.to_string()),
        ("Cache-Control", "no-store".to_string()),
    ];
    headers.extend(answer.headers.iter().map(|(n, v)| (*n, v.clone())));
    if let Err(e) = http::write_answer(stream, answer.status, &headers, &answer.body, with_body) {
        eprintln!("profuse view: reply failed: {e}");
    }
}

/// Headers every answer carries: no MIME sniffing, no framing by other pages, no referrer.
const SECURITY_HEADERS: [(&str, &str); 4] = [
    ("X-Content-Type-Options", "nosniff"),
    ("X-Frame-Options", "DENY"),
    ("Content-Security-Policy", "frame-ancestors 'none'"),
    ("Referrer-Policy", "no-referrer"),
];

/// The answer to one request: `method`, the `Host` header (if any) and `url`, for a server
/// listening on `addr` (see the module documentation for the rules before [`answer`]).
pub fn respond(
    scene: &ViewScene,
    method: &str,
    host: Option<&str>,
    url: &str,
    addr: SocketAddr,
) -> Answer {
    let out = if method != "GET" && method != "HEAD" {
        let mut a = Answer::error(405, format!("method {method} not allowed: GET or HEAD"));
        a.headers.push(("Allow", "GET, HEAD".into()));
        a
    } else if !host_allowed(host, addr) {
        Answer::error(
            421,
            format!(
                "Host {:?} is not this server's loopback address (open {})",
                host.unwrap_or(""),
                format_args!("http://{addr}/")
            ),
        )
    } else {
        answer(scene, url)
    };
    hardened(out)
}

/// `answer` with the headers every answer carries ([`SECURITY_HEADERS`]).
fn hardened(mut answer: Answer) -> Answer {
    answer
        .headers
        .extend(SECURITY_HEADERS.iter().map(|(n, v)| (*n, (*v).to_string())));
    answer
}

/// Whether a request with this `Host` header may be answered by a server on `addr`: any
/// host when the server listens beyond loopback (the user chose to serve others), else a
/// loopback name (with the server's port, when a port is given).
pub fn host_allowed(host: Option<&str>, addr: SocketAddr) -> bool {
    if !addr.ip().is_loopback() {
        return true;
    }
    let Some(host) = host else { return false };
    let (name, port) = match host.rsplit_once(':') {
        Some((n, p)) if !n.ends_with(':') && (n.starts_with('[') == n.ends_with(']')) => {
            (n, Some(p))
        }
        _ => (host, None),
    };
    // The name is what tells a rebinding page apart; a port, when given, must be ours.
    let port_ok = port.is_none_or(|p| p.parse::<u16>().ok() == Some(addr.port()));
    let name = name.trim_start_matches('[').trim_end_matches(']');
    let loopback = name.eq_ignore_ascii_case("localhost")
        || name.parse::<IpAddr>().is_ok_and(|ip| ip.is_loopback());
    port_ok && loopback
}

/// The answer to a GET of `url` (path and query string).
pub fn answer(scene: &ViewScene, url: &str) -> Answer {
    let (path, query) = url.split_once('?').unwrap_or((url, ""));
    let result = match path {
        "/" | "/index.html" => Ok(Answer::ok("text/html; charset=utf-8", INDEX_HTML.into())),
        "/app.js" => Ok(Answer::ok("text/javascript", APP_JS.into())),
        "/gsplat.js" => Ok(Answer::ok("text/javascript", GSPLAT_JS.into())),
        "/scene.splat" => Ok(Answer::ok(
            "application/octet-stream",
            scene.splat().to_vec(),
        )),
        "/api/scene" => Ok(json_answer(&scene.info())),
        "/api/select" => select_answer(scene, query),
        "/api/click" => click_answer(scene, query),
        "/api/export.ply" => export_answer(scene, query),
        _ => return Answer::error(404, format!("no such page: {path}")),
    };
    // The query crate's errors here come from the request (a click on no mask, a view
    // out of range): the client's to fix, like a bad parameter.
    result.unwrap_or_else(|e| match e {
        ViewError::BadRequest { .. } | ViewError::Query(_) => {
            Answer::error(400, without_server_paths(scene, &e.to_string()))
        }
        _ => {
            // The detail names files on the server: for its operator, not for the page.
            eprintln!("profuse view: {path}: {e}");
            Answer::error(
                500,
                "internal error (the server printed the detail on its stderr)".into(),
            )
        }
    })
}

/// `text` with the output's file paths replaced by their file names: the page needs to know
/// which file, not where the server keeps it.
fn without_server_paths(scene: &ViewScene, text: &str) -> String {
    let mut out = text.to_string();
    for p in scene.paths().files() {
        if let Some(name) = p.file_name() {
            out = out.replace(&p.display().to_string(), &name.to_string_lossy());
        }
    }
    out
}

fn json_answer(info: &SceneInfo) -> Answer {
    // Serialising plain structs of numbers and strings cannot fail.
    let body = serde_json::to_vec(info).unwrap_or_default();
    Answer::ok("application/json", body)
}

fn ids_answer(ids: &[u32]) -> Answer {
    let body = ids.iter().flat_map(|id| id.to_le_bytes()).collect();
    Answer::ok("application/octet-stream", body)
}

fn select_answer(scene: &ViewScene, query: &str) -> Result<Answer> {
    Ok(ids_answer(&prompt_selection(scene, &Params::parse(query))?))
}

fn prompt_selection(scene: &ViewScene, params: &Params) -> Result<Vec<u32>> {
    let prompt = params.get("prompt")?;
    let threshold = params.number("threshold")?;
    scene.select_prompt(&prompt, threshold as f32)
}

fn click_selection(scene: &ViewScene, params: &Params) -> Result<(ClickTarget, Vec<u32>)> {
    let view = params.number("view")?;
    if !(view >= 0.0 && view.fract() == 0.0 && view < u32::MAX as f64) {
        return Err(bad("view", "a view index"));
    }
    let click = Click {
        view: view as usize,
        x: params.number("x")?,
        y: params.number("y")?,
    };
    let threshold = params.number("threshold")?;
    scene.select_click(click, threshold as f32)
}

fn click_answer(scene: &ViewScene, query: &str) -> Result<Answer> {
    let (target, ids) = click_selection(scene, &Params::parse(query))?;
    let mut answer = ids_answer(&ids);
    answer.headers.push((
        "X-Click",
        serde_json::to_string(&target).unwrap_or_default(),
    ));
    Ok(answer)
}

fn export_answer(scene: &ViewScene, query: &str) -> Result<Answer> {
    let params = Params::parse(query);
    let ids = if params.get("prompt").is_ok() {
        prompt_selection(scene, &params)?
    } else {
        click_selection(scene, &params)?.1
    };
    let mut answer = Answer::ok("application/octet-stream", scene.export_ply(&ids)?);
    answer.headers.push((
        "Content-Disposition",
        "attachment; filename=\"selection.ply\"".into(),
    ));
    Ok(answer)
}

fn bad(name: &str, reason: &str) -> ViewError {
    ViewError::BadRequest {
        name: name.into(),
        reason: reason.into(),
    }
}

/// Decoded `name=value` pairs of a query string.
struct Params(Vec<(String, String)>);

impl Params {
    fn parse(query: &str) -> Params {
        Params(
            query
                .split('&')
                .filter(|p| !p.is_empty())
                .map(|p| {
                    let (k, v) = p.split_once('=').unwrap_or((p, ""));
                    (percent_decode(k), percent_decode(v))
                })
                .collect(),
        )
    }

    fn get(&self, name: &str) -> Result<String> {
        self.0
            .iter()
            .find(|(k, _)| k == name)
            .map(|(_, v)| v.clone())
            .ok_or_else(|| bad(name, "missing"))
    }

    fn number(&self, name: &str) -> Result<f64> {
        let text = self.get(name)?;
        text.parse::<f64>()
            .ok()
            .filter(|v| v.is_finite())
            .ok_or_else(|| bad(name, &format!("a finite number, got {text:?}")))
    }
}

/// Decodes `%XX` escapes and `+` (a space in form encoding); invalid escapes stay as
/// they are, invalid UTF-8 becomes U+FFFD.
pub fn percent_decode(s: &str) -> String {
    let bytes = s.as_bytes();
    let mut out = Vec::with_capacity(bytes.len());
    let mut i = 0;
    while i < bytes.len() {
        let hex = bytes
            .get(i + 1..i + 3)
            .and_then(|h| std::str::from_utf8(h).ok())
            .and_then(|h| u8::from_str_radix(h, 16).ok());
        match (bytes[i], hex) {
            (b'%', Some(v)) => {
                out.push(v);
                i += 3;
            }
            (b'+', _) => {
                out.push(b' ');
                i += 1;
            }
            (b, _) => {
                out.push(b);
                i += 1;
            }
        }
    }
    String::from_utf8_lossy(&out).into_owned()
}
