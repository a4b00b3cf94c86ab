//! Hostile inputs, mutated by the thousand: MCAP logs (byte flips, truncations, crafted length
//! fields, in a zstd and an uncompressed log) and graph files (byte flips, truncations,
//! absurd numbers, overlong lines). Nothing may panic or hang, no read may allocate beyond a
//! bound derived from the input's length (a counting global allocator measures every case), a
//! log read that succeeds returns exactly the recorded steps (a prefix of them when the file
//! is cut), and a single damaged byte inside the data section is never accepted as a complete
//! log with other content.
//!
//! The logs are recorded here by the library's own recorder from simulated worlds; no dataset
//! is used.

mod common;

use std::alloc::{GlobalAlloc, Layout, System};
use std::sync::atomic::{AtomicUsize, Ordering};

use common::SharedSink;
use so2lin::batch::{BatchConfig, screen, solve};
use so2lin::estimate::OrientationEstimator;
use so2lin::io::{ReadOptions, read_graph_from};
use so2lin::log::{LogContents, LogError, LogOptions, Recorder, read_log, record_limit, replay};
use so2lin::online::{OnlineConfig, OnlineEstimator};
use so2lin::refine::RefineConfig;
use so2lin::sim::{SimConfig, simulate};

/// Counts live heap bytes and their peak, to bound what one read allocates.
struct Counting;

static LIVE: AtomicUsize = AtomicUsize::new(0);
static PEAK: AtomicUsize = AtomicUsize::new(0);

unsafe impl GlobalAlloc for Counting {
    unsafe fn alloc(&self, layout: Layout) -> *mut u8 {
        let p = unsafe { System.alloc(layout) };
        if !p.is_null() {
            let now = LIVE.fetch_add(layout.size(), Ordering::Relaxed) + layout.size();
            PEAK.fetch_max(now, Ordering::Relaxed);
        }
        p
    }
    unsafe fn dealloc(&self, ptr: *mut u8, layout: Layout) {
        unsafe { System.dealloc(ptr, layout) };
        LIVE.fetch_sub(layout.size(), Ordering::Relaxed);
    }
}

#[global_allocator]
static ALLOCATOR: Counting = Counting;

/// Run `f` and return its result with the peak heap growth it caused, in bytes. Tests in this
/// file run one at a time (a mutex), so the counters are this closure's.
fn peak_growth<T>(f: impl FnOnce() -> T) -> (T, usize) {
    let base = LIVE.load(Ordering::Relaxed);
    PEAK.store(base, Ordering::Relaxed);
    let out = f();
    (out, PEAK.load(Ordering::Relaxed).saturating_sub(base))
}

static SERIAL: std::sync::Mutex<()> = std::sync::Mutex::new(());

/// A small deterministic generator (xorshift64*), so every run mutates the same way.
struct Rng(u64);

impl Rng {
    fn next(&mut self) -> u64 {
        self.0 ^= self.0 >> 12;
        self.0 ^= self.0 << 25;
        self.0 ^= self.0 >> 27;
        self.0.wrapping_mul(0x2545_F491_4F6C_DD1D)
    }
    fn below(&mut self, n: usize) -> usize {
        (self.next() % n.max(1) as u64) as usize
    }
}

/// A log of a simulated world recorded by the library's recorder (zstd chunks).
fn recorded_log(poses: usize, seed: u64) -> Vec<u8> {
    let world = simulate(&SimConfig::new(poses, seed)).unwrap();
    let sink = SharedSink::default();
    let config = OnlineConfig::default();
    let mut est = OnlineEstimator::new(config).unwrap();
    let options = LogOptions {
        snapshot_every: 40,
        flush_every: 16,
        flush_on_loop_closure: true,
        ..LogOptions::default()
    };
    let mut rec = Recorder::new(Box::new(sink.clone()), &config, "fuzz", options).unwrap();
    for (k, e) in world.graph.edges().iter().enumerate() {
        rec.add_edge_at(&mut est, *e, k as u64 * 100_000_000)
            .unwrap();
    }
    rec.finish(&mut est).unwrap();
    sink.bytes()
}

/// The same messages and metadata re-written without compression, so crafted lengths reach
/// the records inside chunks too.
fn uncompressed_copy(bytes: &[u8]) -> Vec<u8> {
    let mut out = std::io::Cursor::new(Vec::new());
    let mut w = mcap::WriteOptions::new()
        .compression(None)
        .chunk_size(Some(4096))
        .create(&mut out)
        .unwrap();
    let mut channels = std::collections::BTreeMap::new();
    for r in mcap::read::LinearReader::new(bytes).unwrap() {
        if let mcap::records::Record::Metadata(m) = r.unwrap() {
            w.write_metadata(&m).unwrap();
        }
    }
    for m in mcap::MessageStream::new(bytes).unwrap() {
        let m = m.unwrap();
        let id = *channels.entry(m.channel.id).or_insert_with(|| {
            let schema = m.channel.schema.as_ref().unwrap();
            let s = w
                .add_schema(&schema.name, &schema.encoding, &schema.data)
                .unwrap();
            w.add_channel(
                s,
                &m.channel.topic,
                &m.channel.message_encoding,
                &Default::default(),
            )
            .unwrap()
        });
        let header = mcap::records::MessageHeader {
            channel_id: id,
            sequence: m.sequence,
            log_time: m.log_time,
            publish_time: m.publish_time,
        };
        w.write_to_known_channel(&header, &m.data).unwrap();
    }
    w.finish().unwrap();
    drop(w);
    out.into_inner()
}

/// Offsets of every record's 8-byte length field at file level, and of the chunk header's
/// size fields (uncompressed size, compression name length, compressed size).
fn length_fields(bytes: &[u8]) -> Vec<usize> {
    let mut at = 8;
    let mut out = Vec::new();
    while at + 9 <= bytes.len() {
        let op = bytes[at];
        let len = u64::from_le_bytes(bytes[at + 1..at + 9].try_into().unwrap()) as usize;
        out.push(at + 1);
        if op == 0x06 {
            // Chunk: start, end (16 bytes), uncompressed size, CRC, name length, name, size.
            let body = at + 9;
            out.push(body + 16);
            out.push(body + 28);
            let name = u32::from_le_bytes(bytes[body + 28..body + 32].try_into().unwrap());
            out.push(body + 32 + name as usize);
        }
        at = match at.checked_add(9 + len) {
            Some(n) => n,
            None => break,
        };
        if op == 0x02 {
            break; // footer
        }
    }
    out
}

/// How one mutated log may be damaged.
fn mutate_log(rng: &mut Rng, original: &[u8], fields: &[usize]) -> (Vec<u8>, bool) {
    let mut b = original.to_vec();
    match rng.below(10) {
        // One flipped byte: the single-damage case whose content is checked.
        0..=4 => {
            let at = rng.below(b.len());
            b[at] ^= 1 + rng.below(255) as u8;
            (b, true)
        }
        // Several flips.
        5 => {
            for _ in 0..2 + rng.below(6) {
                let at = rng.below(b.len());
                b[at] ^= 1 + rng.below(255) as u8;
            }
            (b, false)
        }
        // A cut.
        6 | 7 => {
            b.truncate(rng.below(b.len()));
            (b, true)
        }
        // A crafted length field.
        _ => {
            let at = fields[rng.below(fields.len())];
            let len = b.len() as u64;
            let value = match rng.below(7) {
                0 => u64::MAX,
                1 => 1 << 63,
                2 => len * 1000,
                3 => 40_000_000_000_000_000,
                4 => 0,
                5 => u64::from_le_bytes(b[at..at + 8].try_into().unwrap()).wrapping_add(1),
                _ => rng.next(),
            };
            let n = (b.len() - at).min(8);
            b[at..at + n].copy_from_slice(&value.to_le_bytes()[..n]);
            (b, false)
        }
    }
}

/// What a successful read of a damaged log may return: the recorded steps, or a prefix of them
/// when the read reports a cut.
fn check_content(got: &LogContents, want: &LogContents, case: usize) {
    let n = got.steps.len();
    assert!(
        n <= want.steps.len(),
        "case {case}: more steps than recorded"
    );
    assert_eq!(got.edges[..], want.edges[..n], "case {case}: edges altered");
    assert_eq!(got.steps[..], want.steps[..n], "case {case}: steps altered");
    assert_eq!(got.metadata, want.metadata, "case {case}: metadata altered");
    if got.truncated.is_none() {
        assert_eq!(n, want.steps.len(), "case {case}: steps lost without a cut");
    }
}

#[test]
fn mutated_logs_never_panic_allocate_unboundedly_or_pass_altered_content() {
    let _serial = SERIAL.lock().unwrap_or_else(|e| e.into_inner());
    let zstd = recorded_log(60, 5);
    let plain = uncompressed_copy(&zstd);
    let mut rng = Rng(0x005e_ed0f_1065);
    let mut outcomes = [0usize; 3]; // ok, cut, error
    let mut corrupt = 0;
    for original in [&zstd, &plain] {
        let want = read_log(original).unwrap();
        assert!(want.truncated.is_none() && want.steps.len() > 60);
        let fields = length_fields(original);
        assert!(fields.len() > 10);
        for case in 0..6000 {
            let (bytes, single) = mutate_log(&mut rng, original, &fields);
            let (result, peak) = peak_growth(|| read_log(&bytes));
            // Bytes read are bounded by the record limit (one decompressed chunk or record at a
            // time) plus the parsed content, itself a few times the file.
            let bound = 2 * record_limit(bytes.len()) + 64 * bytes.len();
            assert!(
                peak <= bound,
                "case {case}: read_log allocated {peak} > {bound} bytes"
            );
            match result {
                Ok(log) => {
                    outcomes[usize::from(log.truncated.is_some())] += 1;
                    if single {
                        check_content(&log, &want, case);
                    }
                    if case % 50 == 0 {
                        let _ = replay(&log, true);
                    }
                }
                Err(e) => {
                    outcomes[2] += 1;
                    corrupt += usize::from(matches!(e, LogError::Corrupt { .. }));
                    assert!(!e.to_string().is_empty());
                }
            }
        }
    }
    // Every kind of outcome was exercised.
    assert!(outcomes.iter().all(|&n| n > 100), "{outcomes:?}");
    assert!(corrupt > 1000, "{corrupt} corrupt of {outcomes:?}");
}

#[test]
fn a_flipped_byte_in_a_chunk_is_corruption_not_a_verified_replay() {
    let _serial = SERIAL.lock().unwrap_or_else(|e| e.into_inner());
    let bytes = recorded_log(60, 5);
    let want = read_log(&bytes).unwrap();
    // Flip each byte of the largest chunk's compressed data in turn.
    let mut at = 8;
    let mut chunk = (0, 0);
    while at + 9 <= bytes.len() {
        let len = u64::from_le_bytes(bytes[at + 1..at + 9].try_into().unwrap()) as usize;
        if bytes[at] == 0x06 && len > chunk.1 {
            chunk = (at, len);
        }
        if bytes[at] == 0x0F {
            break; // data end
        }
        at += 9 + len;
    }
    let (start, len) = chunk;
    assert!(len > 100);
    let mut corrupt = 0;
    for k in (start + 9 + 60)..(start + 9 + len) {
        let mut b = bytes.clone();
        b[k] ^= 0x10;
        match read_log(&b) {
            Ok(log) => check_content(&log, &want, k),
            Err(LogError::Corrupt {
                offset,
                intact_steps,
                ..
            }) => {
                assert!(offset as usize <= b.len() && intact_steps <= want.steps.len());
                corrupt += 1;
            }
            Err(e) => panic!("byte {k}: {e}"),
        }
    }
    assert!(corrupt > len / 2, "{corrupt} of {len}");
}

/// A small graph file as text, with a few quirks the reader must handle.
fn sample_graph() -> Vec<u8> {
    let world = simulate(&SimConfig::new(40, 7)).unwrap();
    let mut out = Vec::new();
    so2lin::io::write_g2o(&mut out, &world.graph, None).unwrap();
    out.extend_from_slice(b"EQUIV 4 5\nLANDMARK 1 2 3\n# comment\n");
    out
}

const ABSURD: [&str; 14] = [
    "1e300",
    "-1e300",
    "1e20",
    "1e-300",
    "4.9e-324",
    "nan",
    "inf",
    "-0",
    "18446744073709551615",
    "18446744073709551616",
    "-1",
    "6.6e6",
    "1e-12",
    "x",
];

fn mutate_graph(rng: &mut Rng, original: &[u8]) -> Vec<u8> {
    let mut b = original.to_vec();
    match rng.below(8) {
        0..=2 => {
            for _ in 0..1 + rng.below(4) {
                let at = rng.below(b.len());
                b[at] ^= 1 + rng.below(255) as u8;
            }
        }
        3 => b.truncate(rng.below(b.len())),
        4 => {
            // An overlong line somewhere.
            let at = rng.below(b.len());
            let long = vec![b'7'; so2lin::io::MAX_LINE_BYTES + rng.below(3)];
            b.splice(at..at, long);
        }
        _ => {
            // Replace a whitespace-separated token by an absurd value.
            let text = String::from_utf8_lossy(&b).into_owned();
            let mut tokens: Vec<&str> = text.split(' ').collect();
            for _ in 0..1 + rng.below(3) {
                let k = rng.below(tokens.len());
                tokens[k] = ABSURD[rng.below(ABSURD.len())];
            }
            b = tokens.join(" ").into_bytes();
        }
    }
    b
}

#[test]
fn mutated_graph_files_never_panic_or_allocate_unboundedly() {
    let _serial = SERIAL.lock().unwrap_or_else(|e| e.into_inner());
    let original = sample_graph();
    let mut rng = Rng(0x6a7a_9e11);
    let config = BatchConfig::default();
    let (mut read, mut errors) = (0, 0);
    for case in 0..10_000 {
        let bytes = mutate_graph(&mut rng, &original);
        let (result, peak) =
            peak_growth(|| read_graph_from(&bytes[..], "fuzz", ReadOptions::default()));
        // A line is never held beyond MAX_LINE_BYTES (+1), and the graph is a few times the
        // text it came from.
        let bound = 2 * so2lin::io::MAX_LINE_BYTES + 64 * original.len();
        assert!(
            peak <= bound,
            "case {case}: read allocated {peak} > {bound} bytes"
        );
        match result {
            Ok((graph, _)) => {
                read += 1;
                // Every accepted graph screens and solves to an answer or a typed error.
                if case % 10 == 0
                    && graph.edge_count() > 0
                    && let (Ok(r), Ok(orient)) =
                        (screen(&graph, &config), OrientationEstimator::new(&graph))
                    && let Some(h) = r.hypotheses.first()
                {
                    let _ = solve(&graph, &r, &orient, h, &RefineConfig::default());
                }
            }
            Err(e) => {
                errors += 1;
                assert!(e.line >= 1, "case {case}: {e}");
            }
        }
    }
    assert!(read > 1000 && errors > 1000, "{read} read, {errors} errors");
}
