//! The relay's data path compiled: a measuring probe for `benchmarks/peer_latency.py`, not
//! a relay (issue 19: "say what it would take if Python cannot get there").
//!
//! It does per message what `fleetctl server` does on the path of a relayed frame, in
//! Rust: parse the WebSocket frame and unmask it, inflate it when the robot deflated it
//! (permessage-deflate, negotiated as `fleetctl.linkdeflate.RelayDeflateFactory` answers),
//! build one server frame and write it to every subscriber, and answer the client's ack
//! pings. What it leaves out is all of the relay's logic (authentication, sessions,
//! permissions, topic routing, priorities, queues, latched topics): a subscription frame
//! (whatever its pattern) makes its sender a receiver of every data frame of the others;
//! text frames are ignored. The benchmark
//! puts the same client, load and consumer on both ends, so the difference between the
//! two runs is the hop.
//!
//! One thread per connection, blocking sockets: a read wakes its thread as an epoll wait
//! would, and the write to each subscriber happens in the read that brought the frame,
//! as the Python relay's write-through does.
//!
//! Usage: `fleetctl-compiled-hop HOST:PORT` (prints `listening on HOST:PORT`).

use std::io::{self, BufRead, BufReader, Read, Write};
use std::net::{TcpListener, TcpStream};
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::{Arc, Mutex};
use std::thread;

use base64::Engine;
use flate2::{Decompress, FlushDecompress};
use sha1::{Digest, Sha1};

const WS_GUID: &str = "258EAFA5-E914-47DA-95CA-C5AB0DC85B11";
// What the Python relay answers to the robot's offer (fleetctl/linkdeflate.py).
const DEFLATE_ANSWER: &str =
    "permessage-deflate; server_no_context_takeover; client_max_window_bits=15";
const MAX_MESSAGE_BYTES: usize = 64 * 1024 * 1024;

const OP_CONT: u8 = 0x0;
const OP_BINARY: u8 = 0x2;
const OP_CLOSE: u8 = 0x8;
const OP_PING: u8 = 0x9;

struct Conn {
    id: u64,
    writer: Mutex<TcpStream>,
}

type Subscribers = Arc<Mutex<Vec<Arc<Conn>>>>;

fn main() {
    let addr = std::env::args()
        .nth(1)
        .unwrap_or_else(|| "127.0.0.1:0".to_string());
    let listener = TcpListener::bind(&addr).unwrap_or_else(|e| {
        eprintln!("fleetctl-compiled-hop: cannot listen on {addr}: {e}");
        std::process::exit(2);
    });
    println!(
        "listening on {}",
        listener.local_addr().expect("bound address")
    );
    io::stdout().flush().ok();
    let subscribers: Subscribers = Arc::new(Mutex::new(Vec::new()));
    let ids = AtomicU64::new(1);
    for stream in listener.incoming() {
        let Ok(stream) = stream else { continue };
        let id = ids.fetch_add(1, Ordering::Relaxed);
        let subs = Arc::clone(&subscribers);
        thread::spawn(move || {
            if let Err(e) = serve(stream, id, &subs) {
                eprintln!("conn#{id}: {e}");
            }
            subs.lock().expect("subscribers").retain(|c| c.id != id);
        });
    }
}

fn serve(stream: TcpStream, id: u64, subscribers: &Subscribers) -> io::Result<()> {
    stream.set_nodelay(true)?;
    let conn = Arc::new(Conn {
        id,
        writer: Mutex::new(stream.try_clone()?),
    });
    let mut reader = BufReader::with_capacity(256 * 1024, stream);
    let deflate = handshake(&mut reader, &conn)?;
    let mut inflater = deflate.then(|| Decompress::new(false));
    let mut message: Vec<u8> = Vec::new(); // a message continued over several frames
    let mut message_op = 0u8;
    let mut message_deflated = false;
    let mut subscribed = false;
    loop {
        let (fin, rsv1, opcode, payload) = read_frame(&mut reader)?;
        match opcode {
            OP_PING => send(&conn, 0xA, &payload)?,
            OP_CLOSE => {
                send(&conn, OP_CLOSE, &payload[..payload.len().min(2)])?;
                return Ok(());
            }
            0x1 | OP_BINARY | OP_CONT => {
                if opcode != OP_CONT {
                    message_op = opcode;
                    message_deflated = rsv1;
                    message.clear();
                }
                if !fin {
                    if message.len() + payload.len() > MAX_MESSAGE_BYTES {
                        return Err(io::Error::new(
                            io::ErrorKind::InvalidData,
                            "message too big",
                        ));
                    }
                    message.extend_from_slice(&payload);
                    continue;
                }
                let whole = if opcode == OP_CONT {
                    message.extend_from_slice(&payload);
                    std::mem::take(&mut message)
                } else {
                    payload
                };
                let data = match (&mut inflater, message_deflated) {
                    (Some(d), true) => inflate(d, &whole)?,
                    _ => whole,
                };
                if message_op == OP_BINARY && is_subscription(&data) {
                    if !subscribed {
                        subscribed = true;
                        subscribers
                            .lock()
                            .expect("subscribers")
                            .push(Arc::clone(&conn));
                    }
                } else if message_op == OP_BINARY {
                    relay(&data, id, subscribers);
                }
            }
            _ => {} // pongs
        }
    }
}

/// A Robofleet subscription frame (`fleetctl.wire.control.encode_subscription`), told by
/// its type string in the frame's metadata rather than parsed: enough for a probe.
fn is_subscription(frame: &[u8]) -> bool {
    const TYPE: &[u8] = b"amrl_msgs/msg/RobofleetSubscription";
    frame.windows(TYPE.len()).any(|w| w == TYPE)
}

/// Answers the upgrade; true when permessage-deflate was offered (and so accepted).
fn handshake(reader: &mut BufReader<TcpStream>, conn: &Conn) -> io::Result<bool> {
    let mut key = None;
    let mut deflate = false;
    let mut line = String::new();
    loop {
        line.clear();
        if reader.read_line(&mut line)? == 0 {
            return Err(io::Error::new(
                io::ErrorKind::UnexpectedEof,
                "closed in the upgrade",
            ));
        }
        let trimmed = line.trim_end();
        if trimmed.is_empty() {
            break;
        }
        if let Some((name, value)) = trimmed.split_once(':') {
            let name = name.trim().to_ascii_lowercase();
            if name == "sec-websocket-key" {
                key = Some(value.trim().to_string());
            } else if name == "sec-websocket-extensions" && value.contains("permessage-deflate") {
                deflate = true;
            }
        }
    }
    let key = key.ok_or_else(|| io::Error::new(io::ErrorKind::InvalidData, "no key"))?;
    let mut sha = Sha1::new();
    sha.update(key.as_bytes());
    sha.update(WS_GUID.as_bytes());
    let accept = base64::engine::general_purpose::STANDARD.encode(sha.finalize());
    let mut response = format!(
        "HTTP/1.1 101 Switching Protocols\r\nUpgrade: websocket\r\nConnection: Upgrade\r\n\
         Sec-WebSocket-Accept: {accept}\r\n"
    );
    if deflate {
        response.push_str(&format!("Sec-WebSocket-Extensions: {DEFLATE_ANSWER}\r\n"));
    }
    response.push_str("\r\n");
    conn.writer
        .lock()
        .expect("writer")
        .write_all(response.as_bytes())?;
    Ok(deflate)
}

fn read_frame(reader: &mut BufReader<TcpStream>) -> io::Result<(bool, bool, u8, Vec<u8>)> {
    let mut head = [0u8; 2];
    reader.read_exact(&mut head)?;
    let fin = head[0] & 0x80 != 0;
    let rsv1 = head[0] & 0x40 != 0;
    let opcode = head[0] & 0x0F;
    let masked = head[1] & 0x80 != 0;
    let mut len = u64::from(head[1] & 0x7F);
    if len == 126 {
        let mut b = [0u8; 2];
        reader.read_exact(&mut b)?;
        len = u64::from(u16::from_be_bytes(b));
    } else if len == 127 {
        let mut b = [0u8; 8];
        reader.read_exact(&mut b)?;
        len = u64::from_be_bytes(b);
    }
    if len > MAX_MESSAGE_BYTES as u64 {
        return Err(io::Error::new(io::ErrorKind::InvalidData, "frame too big"));
    }
    let mut mask = [0u8; 4];
    if masked {
        reader.read_exact(&mut mask)?;
    }
    let mut payload = vec![0u8; len as usize];
    reader.read_exact(&mut payload)?;
    if masked {
        for (i, b) in payload.iter_mut().enumerate() {
            *b ^= mask[i & 3];
        }
    }
    Ok((fin, rsv1, opcode, payload))
}

/// RFC 7692 section 7.2.2: append the empty stored block's tail, inflate with the
/// connection's window (context takeover).
fn inflate(d: &mut Decompress, data: &[u8]) -> io::Result<Vec<u8>> {
    let mut input = Vec::with_capacity(data.len() + 4);
    input.extend_from_slice(data);
    input.extend_from_slice(&[0x00, 0x00, 0xFF, 0xFF]);
    let mut out = Vec::with_capacity(data.len() * 4 + 256);
    let mut pos = 0usize;
    loop {
        if out.len() == out.capacity() {
            out.reserve(out.capacity());
        }
        let before = d.total_in();
        d.decompress_vec(&input[pos..], &mut out, FlushDecompress::Sync)
            .map_err(|e| io::Error::new(io::ErrorKind::InvalidData, e))?;
        pos += (d.total_in() - before) as usize;
        if out.len() > MAX_MESSAGE_BYTES {
            return Err(io::Error::new(
                io::ErrorKind::InvalidData,
                "inflates too big",
            ));
        }
        if pos >= input.len() && out.len() < out.capacity() {
            return Ok(out);
        }
    }
}

fn frame(opcode: u8, payload: &[u8]) -> Vec<u8> {
    let mut out = Vec::with_capacity(payload.len() + 10);
    out.push(0x80 | opcode);
    match payload.len() {
        n if n < 126 => out.push(n as u8),
        n if n <= 0xFFFF => {
            out.push(126);
            out.extend_from_slice(&(n as u16).to_be_bytes());
        }
        n => {
            out.push(127);
            out.extend_from_slice(&(n as u64).to_be_bytes());
        }
    }
    out.extend_from_slice(payload);
    out
}

fn send(conn: &Conn, opcode: u8, payload: &[u8]) -> io::Result<()> {
    conn.writer
        .lock()
        .expect("writer")
        .write_all(&frame(opcode, payload))
}

/// One server frame, written to every subscriber but the sender in this read.
fn relay(data: &[u8], from: u64, subscribers: &Subscribers) {
    let bytes = frame(OP_BINARY, data);
    let receivers: Vec<Arc<Conn>> = subscribers.lock().expect("subscribers").clone();
    for conn in receivers.iter().filter(|c| c.id != from) {
        // A subscriber that cannot take the write ends its own connection; its thread
        // notices and removes it.
        if let Ok(mut w) = conn.writer.lock() {
            if w.write_all(&bytes).is_err() {
                let _ = w.shutdown(std::net::Shutdown::Both);
            }
        }
    }
}
