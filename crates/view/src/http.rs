//! The little HTTP/1.1 the viewer needs, with the limits a server on a user's machine must
//! have: one request per connection (`Connection: close`), a request head of at most
//! [`MAX_HEAD_BYTES`] read within [`READ_TIMEOUT`], no request body ever read (the viewer
//! takes none: a declared body does not make the server wait or allocate), at most
//! [`MAX_CONNECTIONS`] connections served at once (503 beyond), and an accept loop that
//! outlives any error (running out of file descriptors pauses it, never ends it).
//!
//! tiny_http, used before, had none of these: a POST declaring a 1 TB body aborted the
//! process when the request was dropped (it allocated the whole declared length to drain
//! it), a 100 MB header line was buffered whole, a client that never finished its request
//! held a thread forever, and one accept error ended the accept thread for good.

use std::io::{Read, Write};
use std::net::TcpStream;
use std::time::Duration;

/// The largest request head (request line and headers) read; longer heads get 431.
pub const MAX_HEAD_BYTES: usize = 16 * 1024;
/// How long a client may take to send its request head.
pub const READ_TIMEOUT: Duration = Duration::from_secs(10);
/// How long a client may take to accept the answer.
pub const WRITE_TIMEOUT: Duration = Duration::from_secs(60);
/// Connections served at once.
pub const MAX_CONNECTIONS: usize = 64;

/// A request head, as far as the viewer reads it.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct RequestHead {
    /// The method, e.g. `GET`.
    pub method: String,
    /// The target: path and query string.
    pub target: String,
    /// The `Host` header, when there is exactly one.
    pub host: Option<String>,
}

/// Why a request head was not read.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum HeadError {
    /// Longer than [`MAX_HEAD_BYTES`] (answer 431).
    TooLarge,
    /// Not an HTTP/1.x request head (answer 400).
    Malformed,
    /// The client closed the connection, or was too slow (no answer).
    Gone,
}

/// Reads one request head from `stream`: up to the blank line, never more than
/// [`MAX_HEAD_BYTES`], never any of the body.
pub fn read_head(stream: &mut impl Read) -> Result<RequestHead, HeadError> {
    let mut head = Vec::with_capacity(1024);
    let mut byte = [0u8; 1];
    // Byte by byte: a body (or a pipelined request) after the head stays unread, and the
    // head's end is found exactly. Heads are a few hundred bytes.
    while !head.ends_with(b"\r\n\r\n") && !head.ends_with(b"\n\n") {
        if head.len() >= MAX_HEAD_BYTES {
            return Err(HeadError::TooLarge);
        }
        match stream.read(&mut byte) {
            Ok(1) => head.push(byte[0]),
            Ok(_) => return Err(HeadError::Gone),
            Err(e) if e.kind() == std::io::ErrorKind::Interrupted => {}
            Err(_) => return Err(HeadError::Gone),
        }
    }
    parse_head(&head)
}

/// Parses a request head (request line, headers, blank line).
pub fn parse_head(head: &[u8]) -> Result<RequestHead, HeadError> {
    let text = std::str::from_utf8(head).map_err(|_| HeadError::Malformed)?;
    let mut lines = text.split('\n').map(|l| l.trim_end_matches('\r'));
    let request_line = lines.next().ok_or(HeadError::Malformed)?;
    let mut parts = request_line.split(' ');
    let (Some(method), Some(target), Some(version), None) =
        (parts.next(), parts.next(), parts.next(), parts.next())
    else {
        return Err(HeadError::Malformed);
    };
    if method.is_empty() || !target.starts_with('/') || !version.starts_with("HTTP/1.") {
        return Err(HeadError::Malformed);
    }
    let mut hosts = Vec::new();
    for line in lines.filter(|l| !l.is_empty()) {
        let (name, value) = line.split_once(':').ok_or(HeadError::Malformed)?;
        if name.trim().eq_ignore_ascii_case("host") {
            hosts.push(value.trim().to_string());
        }
    }
    Ok(RequestHead {
        method: method.to_string(),
        target: target.to_string(),
        // Two Host headers name no host: refused like a missing one.
        host: (hosts.len() == 1).then(|| hosts.remove(0)),
    })
}

/// The reason phrase of the statuses the viewer answers.
pub fn reason(status: u16) -> &'static str {
    match status {
        200 => "OK",
        400 => "Bad Request",
        404 => "Not Found",
        405 => "Method Not Allowed",
        421 => "Misdirected Request",
        431 => "Request Header Fields Too Large",
        500 => "Internal Server Error",
        503 => "Service Unavailable",
        _ => "Unknown",
    }
}

/// Writes one answer and closes the connection (`Connection: close`); `with_body` false
/// for HEAD. Header names and values are the server's own (no client text reaches them
/// unescaped: values are JSON or fixed strings without line breaks).
pub fn write_answer(
    stream: &mut TcpStream,
    status: u16,
    headers: &[(&str, String)],
    body: &[u8],
    with_body: bool,
) -> std::io::Result<()> {
    let mut head = format!(
        "HTTP/1.1 {status} {}\r\nContent-Length: {}\r\nConnection: close\r\n",
        reason(status),
        body.len()
    );
    for (name, value) in headers {
        let clean: String = value.chars().filter(|c| *c != '\r' && *c != '\n').collect();
        head.push_str(&format!("{name}: {clean}\r\n"));
    }
    head.push_str("\r\n");
    stream.write_all(head.as_bytes())?;
    if with_body {
        stream.write_all(body)?;
    }
    stream.flush()?;
    // Unread request bytes (a declared body) would turn the close into a reset that can
    // lose the answer: say we are done writing first, and let the client close.
    let _ = stream.shutdown(std::net::Shutdown::Write);
    Ok(())
}

#[cfg(test)]
#[allow(clippy::unwrap_used)]
mod tests {
    use super::*;

    #[test]
    fn heads_parse_and_bad_ones_are_named() {
        let h = parse_head(b"GET /api/scene?x=1 HTTP/1.1\r\nHost: localhost:8765\r\n\r\n").unwrap();
        assert_eq!(h.method, "GET");
        assert_eq!(h.target, "/api/scene?x=1");
        assert_eq!(h.host.as_deref(), Some("localhost:8765"));
        let two = parse_head(b"GET / HTTP/1.1\r\nHost: a\r\nhost: b\r\n\r\n").unwrap();
        assert_eq!(two.host, None);
        for bad in [
            &b"GET / HTTP/2\r\n\r\n"[..],
            b"GET\r\n\r\n",
            b"GET / HTTP/1.1 extra\r\n\r\n",
            b"GET http://x/ HTTP/1.1\r\n\r\n",
            b"GET / HTTP/1.1\r\nno colon\r\n\r\n",
        ] {
            assert_eq!(parse_head(bad), Err(HeadError::Malformed), "{bad:?}");
        }
    }

    #[test]
    fn a_head_stops_at_its_end_and_at_the_limit() {
        let mut r: &[u8] = b"GET / HTTP/1.1\r\nHost: h\r\n\r\nBODY-NOT-READ";
        assert_eq!(read_head(&mut r).unwrap().target, "/");
        assert_eq!(r, b"BODY-NOT-READ");
        let long = format!(
            "GET / HTTP/1.1\r\nX: {}\r\n\r\n",
            "a".repeat(MAX_HEAD_BYTES)
        );
        assert_eq!(read_head(&mut long.as_bytes()), Err(HeadError::TooLarge));
        assert_eq!(read_head(&mut &b"GET / HT"[..]), Err(HeadError::Gone));
    }
}
