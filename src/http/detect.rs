//! `POST /detect`: the image as the body (`image/jpeg`, `image/png`) or as
//! the `image` part of a `multipart/form-data` body; options in the query.
//! Answers the detection JSON, or with `format=png` (or `Accept:
//! image/png`) a label map with the detections in `X-Detections` (as many
//! as fit in [`MAX_DETECTIONS_HEADER`]) and all of them in the PNG's
//! `sdhop-detections` text chunk.

use std::io::Cursor;
use std::sync::Arc;
use std::time::{Duration, Instant};

use axum::body::Body;
use axum::extract::multipart::MultipartError;
use axum::extract::{FromRequest, Multipart, RawQuery, Request, State};
use axum::http::{header, HeaderMap, HeaderValue};
use axum::response::{IntoResponse, Response};
use axum::Json;
use serde::Serialize;

use super::error::ApiError;
use super::image::{decode, image_size, IMAGE_TYPES};
use super::state::AppState;
use crate::infer::DetectTask;
use crate::model::Model;
use crate::pipeline::{BoxJson, DetectOptions, DetectResponse, DetectionJson, MaskMode, RleFormat};
use crate::vision::mask::Mask;
use crate::vision::Deadline;

/// Response formats.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Format {
    Json,
    Png,
}

/// The query options of `POST /detect`, checked.
#[derive(Clone, Debug, PartialEq)]
pub struct DetectQuery {
    /// Model names; empty means every loaded model.
    pub models: Vec<String>,
    pub threshold: Option<f64>,
    pub max_detections: Option<usize>,
    pub masks: MaskMode,
    pub format: Option<Format>,
    /// `None`: not given (uncompressed).
    pub rle: Option<RleFormat>,
    pub timeout: Option<Duration>,
    /// Response transfer between the models (see `DetectOptions::transfer`).
    pub transfer: bool,
}

impl DetectQuery {
    /// Parses the raw query; `model` may repeat and holds comma-separated
    /// names. Unknown, repeated (other than `model`) or malformed
    /// parameters are errors.
    pub fn parse(
        raw: Option<&str>,
        max_detections: usize,
        max_timeout: Duration,
    ) -> Result<Self, ApiError> {
        let mut q = DetectQuery {
            models: Vec::new(),
            threshold: None,
            max_detections: None,
            masks: MaskMode::Refined,
            format: None,
            rle: None,
            timeout: None,
            transfer: false,
        };
        let bad = |k: &str, v: &str, why: &str| {
            ApiError::BadRequest(format!(
                "query parameter {}={}: {why}",
                super::error::shorten(k),
                super::error::shorten(v)
            ))
        };
        let mut seen: Vec<String> = Vec::new();
        for (k, v) in form_urlencoded::parse(raw.unwrap_or("").as_bytes()) {
            if k != "model" {
                if seen.iter().any(|s| *s == k) {
                    return Err(bad(
                        &k,
                        &v,
                        "repeated: give it once (only model may repeat)",
                    ));
                }
                seen.push(k.to_string());
            }
            match k.as_ref() {
                "model" => {
                    // ASCII white space only, the class openapi.yaml's
                    // pattern names: a name of other spaces is a name.
                    for name in v
                        .split(',')
                        .map(|n| n.trim_matches(|c: char| c.is_ascii_whitespace()))
                    {
                        if name.is_empty() {
                            return Err(bad(&k, &v, "empty model name"));
                        }
                        if !q.models.iter().any(|m| m == name) {
                            q.models.push(name.to_string());
                        }
                    }
                }
                "threshold" => {
                    let t: f64 = v.parse().map_err(|_| bad(&k, &v, "not a number"))?;
                    if !t.is_finite() {
                        return Err(bad(&k, &v, "must be finite"));
                    }
                    q.threshold = Some(t);
                }
                "max_detections" => {
                    let n: usize = v
                        .parse()
                        .map_err(|_| bad(&k, &v, "not a non-negative integer"))?;
                    if n == 0 || n > max_detections {
                        return Err(bad(&k, &v, &format!("must be in 1..={max_detections}")));
                    }
                    q.max_detections = Some(n);
                }
                "masks" => {
                    q.masks = match v.as_ref() {
                        "refined" => MaskMode::Refined,
                        "raw" => MaskMode::Raw,
                        "both" => MaskMode::Both,
                        "none" => MaskMode::None,
                        _ => return Err(bad(&k, &v, "expected refined, raw, both or none")),
                    }
                }
                "format" => {
                    q.format = Some(match v.as_ref() {
                        "json" => Format::Json,
                        "png" => Format::Png,
                        _ => return Err(bad(&k, &v, "expected json or png")),
                    })
                }
                "rle" => {
                    q.rle = Some(match v.as_ref() {
                        "uncompressed" => RleFormat::Uncompressed,
                        "compressed" => RleFormat::Compressed,
                        _ => return Err(bad(&k, &v, "expected uncompressed or compressed")),
                    })
                }
                "timeout_ms" => {
                    q.timeout = Some(timeout_param(&v, Duration::from_millis(1), max_timeout)?)
                }
                "transfer" => {
                    q.transfer = match v.as_ref() {
                        "true" => true,
                        "false" => false,
                        _ => return Err(bad(&k, &v, "expected true or false")),
                    }
                }
                _ => return Err(bad(&k, &v, "unknown parameter")),
            }
        }
        Ok(q)
    }
}

/// The `timeout_ms` query parameter, checked against the least and the
/// largest allowed.
pub(super) fn timeout_param(
    v: &str,
    min_timeout: Duration,
    max_timeout: Duration,
) -> Result<Duration, ApiError> {
    let least = min_timeout.as_millis().max(1) as u64;
    let limit = max_timeout.as_millis() as u64;
    match v.parse::<u64>() {
        Ok(ms) if ms >= least && ms <= limit => Ok(Duration::from_millis(ms)),
        _ => Err(ApiError::BadRequest(format!(
            "query parameter timeout_ms={}: must be an integer in {least}..={limit}",
            super::error::shorten(v)
        ))),
    }
}

/// When a body did not arrive in time (`timed_out`), the most telling
/// error known without it: a malformed query (`query`), then a media type
/// the route does not take (`media`), else the time-out itself. So a
/// request whose head is already wrong is answered 4xx for it, however
/// short its deadline.
pub(super) fn before_body<T>(
    timed_out: ApiError,
    query: Result<T, ApiError>,
    media: Result<(), ApiError>,
) -> ApiError {
    match (query, media) {
        (Err(e), _) | (Ok(_), Err(e)) => e,
        (Ok(_), Ok(())) => timed_out,
    }
}

/// 415 unless the request's media type is one of `accepted`.
pub(super) fn media_in(headers: &HeaderMap, accepted: &[&str], what: &str) -> Result<(), ApiError> {
    match media_type(headers) {
        Some(t) if accepted.contains(&t.as_str()) => Ok(()),
        other => Err(ApiError::UnsupportedMediaType(format!(
            "send {what}, not {}",
            other.as_deref().unwrap_or("a body without Content-Type")
        ))),
    }
}

/// The models a request names, or all of them.
fn select_models(state: &AppState, names: &[String]) -> Result<Vec<Arc<Model>>, ApiError> {
    if names.is_empty() {
        return Ok(state.models.iter().map(|m| Arc::clone(&m.model)).collect());
    }
    names
        .iter()
        .map(|n| {
            state
                .model(n)
                .map(|m| Arc::clone(&m.model))
                .ok_or_else(|| ApiError::UnknownModel(n.clone()))
        })
        .collect()
}

/// The media type of a request, without parameters, lower case.
pub(super) fn media_type(headers: &HeaderMap) -> Option<String> {
    let v = headers.get(header::CONTENT_TYPE)?.to_str().ok()?;
    Some(v.split(';').next()?.trim().to_ascii_lowercase())
}

impl Format {
    /// The media type of the answer.
    pub fn media_type(self) -> &'static str {
        match self {
            Format::Json => "application/json",
            Format::Png => "image/png",
        }
    }

    fn query_name(self) -> &'static str {
        match self {
            Format::Json => "json",
            Format::Png => "png",
        }
    }
}

/// A weight of the `Accept` header (RFC 9110, 12.4.2): `0` or `1`, or
/// `0.` with up to three digits, or `1.` with up to three zeros.
fn qvalue(text: &str) -> Option<f32> {
    let (int, frac) = text.split_once('.').unwrap_or((text, ""));
    let ok = frac.len() <= 3
        && frac.bytes().all(|b| b.is_ascii_digit())
        && match int {
            "0" => true,
            "1" => frac.bytes().all(|b| b == b'0'),
            _ => false,
        };
    ok.then(|| text.parse().ok()).flatten()
}

/// The media ranges of the request's `Accept` headers with their weights;
/// a range whose `q` is not a weight is left out. `None`: no header, or
/// no usable range in it (every type is then acceptable).
fn accept_ranges(headers: &HeaderMap) -> Option<Vec<(String, f32)>> {
    let mut ranges = Vec::new();
    for value in headers.get_all(header::ACCEPT) {
        let Ok(value) = value.to_str() else { continue };
        for item in value.split(',') {
            let mut parts = item.split(';');
            let range = parts.next().unwrap_or_default().trim().to_ascii_lowercase();
            if range.is_empty() {
                continue;
            }
            let mut q = Some(1.0);
            for p in parts {
                if let Some((k, v)) = p.split_once('=') {
                    if k.trim().eq_ignore_ascii_case("q") {
                        q = qvalue(v.trim());
                        break;
                    }
                }
            }
            if let Some(q) = q {
                ranges.push((range, q));
            }
        }
    }
    (!ranges.is_empty()).then_some(ranges)
}

/// The weight `ranges` give `media_type`: that of the most specific range
/// matching it (`type/subtype`, then `type/*`, then `*/*`; the largest
/// where one is listed twice), 0 when none matches.
fn weight_of(ranges: &[(String, f32)], media_type: &str) -> f32 {
    let main = media_type.split('/').next().unwrap_or_default();
    let wildcard = format!("{main}/*");
    [media_type, wildcard.as_str(), "*/*"]
        .iter()
        .find_map(|want| {
            ranges
                .iter()
                .filter(|(r, _)| r == want)
                .map(|(_, q)| *q)
                .reduce(f32::max)
        })
        .unwrap_or(0.0)
}

/// The answer's format: `format=` when given, else the type `Accept`
/// weighs highest (JSON on a tie or without the header). A format the
/// `Accept` header does not accept (weight 0, or matched by no range) is
/// answered 406 rather than sent: `format=` chooses between acceptable
/// types, it does not override a refusal.
pub fn negotiate(headers: &HeaderMap, asked: Option<Format>) -> Result<Format, ApiError> {
    let Some(ranges) = accept_ranges(headers) else {
        return Ok(asked.unwrap_or(Format::Json));
    };
    let accepted = |f: Format| weight_of(&ranges, f.media_type());
    let listed = || {
        headers
            .get_all(header::ACCEPT)
            .iter()
            .filter_map(|v| v.to_str().ok())
            .collect::<Vec<_>>()
            .join(", ")
    };
    match asked {
        Some(f) if accepted(f) > 0.0 => Ok(f),
        Some(f) => Err(ApiError::NotAcceptable(format!(
            "format={} answers {}, which the Accept header ({}) does not accept",
            f.query_name(),
            f.media_type(),
            super::error::shorten(&listed())
        ))),
        None => {
            let (json, png) = (accepted(Format::Json), accepted(Format::Png));
            if json <= 0.0 && png <= 0.0 {
                Err(ApiError::NotAcceptable(format!(
                    "the Accept header ({}) accepts neither application/json nor image/png, the answers /detect gives",
                    super::error::shorten(&listed())
                )))
            } else if png > json {
                Ok(Format::Png)
            } else {
                Ok(Format::Json)
            }
        }
    }
}

/// Checks the options against the answer's format: a label map is drawn
/// from one mask per detection and its detections carry no masks, so
/// `masks=none` or `both` and `rle` cannot be honoured with it (422).
fn check_format_options(format: Format, query: &DetectQuery) -> Result<(), ApiError> {
    if format != Format::Png {
        return Ok(());
    }
    let conflict = match (query.masks, query.rle) {
        (MaskMode::None, _) => Some("masks=none leaves no mask to draw: ask for masks=refined (the default) or raw"),
        (MaskMode::Both, _) => Some("masks=both gives two masks per detection and a label map draws one: ask for masks=refined (the default) or raw"),
        (_, Some(_)) => Some("rle says how JSON masks are written, and the label map's detections carry none: leave rle out"),
        _ => None,
    };
    match conflict {
        Some(why) => Err(ApiError::Unprocessable(format!(
            "a label map (image/png) answer: {why}"
        ))),
        None => Ok(()),
    }
}

/// The media types of a `/detect` body.
const BODY_TYPES: [&str; 3] = [IMAGE_TYPES[0], IMAGE_TYPES[1], "multipart/form-data"];

/// The most parts of a multipart `/detect` body before its `image` part.
pub const MAX_OTHER_PARTS: usize = 16;

/// The image bytes of a request, within the body limit.
async fn image_bytes(req: Request, limit: usize) -> Result<Vec<u8>, ApiError> {
    let too_large = || ApiError::PayloadTooLarge(format!("the body exceeds {limit} bytes"));
    match media_type(req.headers()).as_deref() {
        Some(t) if IMAGE_TYPES.contains(&t) => {
            let body: Body = req.into_body();
            let bytes = axum::body::to_bytes(body, limit).await.map_err(|e| {
                if is_length_limit(&e) {
                    too_large()
                } else {
                    ApiError::BadRequest(format!("cannot read the body: {e}"))
                }
            })?;
            Ok(bytes.to_vec())
        }
        Some("multipart/form-data") => {
            let mut mp = Multipart::from_request(req, &())
                .await
                .map_err(|e| ApiError::BadRequest(e.body_text()))?;
            // The body is already in memory (see `body::buffer`): the
            // first `image` part is taken and the rest left unparsed; at
            // most MAX_OTHER_PARTS other parts come before it (a body of
            // many empty parts was parsed whole on the runtime's thread).
            let mut others = 0usize;
            while let Some(field) = mp
                .next_field()
                .await
                .map_err(|e| multipart_error(&e, limit))?
            {
                if field.name() == Some("image") {
                    let bytes = field
                        .bytes()
                        .await
                        .map_err(|e| multipart_error(&e, limit))?;
                    return Ok(bytes.to_vec());
                }
                others += 1;
                if others > MAX_OTHER_PARTS {
                    return Err(ApiError::BadRequest(format!(
                        "more than {MAX_OTHER_PARTS} parts before the `image` part"
                    )));
                }
            }
            Err(ApiError::BadRequest(
                "the multipart body has no `image` part".into(),
            ))
        }
        other => {
            let e = ApiError::UnsupportedMediaType(format!(
                "send the image as image/jpeg, image/png or multipart/form-data, not {}",
                other.unwrap_or("a body without Content-Type")
            ));
            Err(e)
        }
    }
}

/// A multipart reading error: 413 past the body limit, else 400.
pub(super) fn multipart_error(e: &MultipartError, limit: usize) -> ApiError {
    if e.status() == axum::http::StatusCode::PAYLOAD_TOO_LARGE {
        ApiError::PayloadTooLarge(format!("the body exceeds {limit} bytes"))
    } else {
        ApiError::BadRequest(e.body_text())
    }
}

/// Whether a body error is the length limit.
fn is_length_limit(e: &axum::Error) -> bool {
    let mut src: Option<&(dyn std::error::Error + 'static)> = Some(e);
    while let Some(s) = src {
        if s.is::<http_body_util::LengthLimitError>() {
            return true;
        }
        src = s.source();
    }
    false
}

/// `POST /detect`.
pub async fn detect(
    State(state): State<Arc<AppState>>,
    RawQuery(raw): RawQuery,
    req: Request,
) -> Result<Response, ApiError> {
    let arrived = Instant::now();
    let cfg = state.config;
    // The query first only for its deadline; its errors are answered once
    // the body is read, so that a client sending a large body with a bad
    // query reads the 400 rather than a reset connection.
    let query = DetectQuery::parse(raw.as_deref(), cfg.max_detections, cfg.max_timeout);
    let timeout = query.as_ref().ok().and_then(|q| q.timeout);
    let deadline = arrived + timeout.unwrap_or(cfg.default_timeout);
    // The whole body before a place in the queue: a client that is not
    // sending holds none.
    let media = media_in(
        req.headers(),
        &BODY_TYPES,
        "the image as image/jpeg, image/png or multipart/form-data",
    );
    let pacing = state.pacing(deadline);
    let req = match super::body::buffer(req, cfg.max_body_bytes, &pacing, state.infer.grace_ended())
        .await
    {
        Ok(req) => req,
        Err(e @ ApiError::RequestTimeout(_)) => return Err(before_body(e, query, media)),
        Err(e) => return Err(e),
    };
    let query = query?;
    let format = negotiate(req.headers(), query.format)?;
    check_format_options(format, &query)?;
    // Admission before decoding or keeping anything: an overload costs no
    // decoding and no memory beyond the queue's.
    let permit = state.infer.admit()?;
    let bytes = image_bytes(req, cfg.max_body_bytes).await?;
    let models = select_models(&state, &query.models)?;
    let limits = cfg.image;
    // The memory its decoding and computation take, reserved from the
    // header's size before anything is decoded (waits for its turn).
    let (w, h) = image_size(&bytes, &limits)?;
    let refs: Vec<&Model> = models.iter().map(|m| m.as_ref()).collect();
    let cost = state.infer.reserve(w, h, &refs, deadline).await?;
    let image = tokio::task::spawn_blocking(move || decode(&bytes, &limits))
        .await
        .map_err(|e| ApiError::Internal(format!("decoder task: {e}")))??;
    let task = DetectTask {
        image: Arc::new(image),
        models,
        opts: DetectOptions {
            threshold: query.threshold,
            // Without a cap asked for, every detection at or above the
            // threshold, up to the server's limit.
            max_detections: Some(query.max_detections.unwrap_or(cfg.max_detections)),
            // A label map is drawn from the masks asked for (refined or raw).
            masks: query.masks,
            prune: true,
            max_pixels: limits.max_pixels,
            region: None,
            deadline: Deadline::NONE,
            transfer: query.transfer,
            label: None,
        },
        cost: Some(cost),
    };
    let resp = state.infer.detect(permit, task, deadline).await?;
    let rle = query.rle.unwrap_or(RleFormat::Uncompressed);
    match format {
        Format::Json if rle == RleFormat::Uncompressed => Ok(Json(resp).into_response()),
        Format::Json => Ok(Json(
            resp.to_json(rle)
                .map_err(|e| ApiError::Internal(format!("JSON: {e}")))?,
        )
        .into_response()),
        Format::Png => label_map_response(&resp),
    }
}

/// One detection in the `X-Detections` header of a PNG answer.
#[derive(Clone, Copy, Serialize)]
struct HeaderDetection<'a> {
    label: &'a str,
    model: &'a str,
    score: f64,
    #[serde(rename = "box")]
    bbox: BoxJson,
}

impl<'a> HeaderDetection<'a> {
    fn of(d: &'a DetectionJson) -> Self {
        Self {
            label: &d.label,
            model: &d.model,
            score: d.score,
            bbox: d.bbox,
        }
    }

    /// Score to 3 decimals, box to 1 (shorter headers).
    fn rounded(&self) -> Self {
        let b = &self.bbox;
        Self {
            score: round(self.score, 3),
            bbox: BoxJson {
                x: round(b.x, 1),
                y: round(b.y, 1),
                width: round(b.width, 1),
                height: round(b.height, 1),
            },
            ..*self
        }
    }
}

/// The largest `X-Detections` header, in bytes: under the 8 KiB that many
/// proxies and HTTP clients allow a header line. The detections that do
/// not fit are left out of it (`X-Detections-Total` says how many there
/// are); all of them are in the PNG's `sdhop-detections` text chunk.
pub const MAX_DETECTIONS_HEADER: usize = 7 << 10;

/// The PNG text chunk (iTXt) that holds every detection of a label map.
pub const DETECTIONS_CHUNK: &str = "sdhop-detections";

/// Rounds to `digits` decimals.
fn round(v: f64, digits: i32) -> f64 {
    let f = 10f64.powi(digits);
    (v * f).round() / f
}

/// A label map the size of the image: 0 is background, `k` the visible
/// pixels of the `k`-th detection (best first; a pixel keeps the best
/// detection's label, so a detection whose visible pixels all belong to
/// better ones, or whose mask is empty, has no pixel in it). 8-bit up to
/// 255 detections, 16-bit above.
pub fn label_map(resp: &DetectResponse) -> Vec<u16> {
    let (w, h) = (resp.image.width, resp.image.height);
    let mut map = vec![0u16; w * h];
    for (k, d) in resp
        .detections
        .iter()
        .enumerate()
        .take(usize::from(u16::MAX))
    {
        let Some(mask) = d
            .mask
            .as_ref()
            .or(d.raw_mask.as_ref())
            .and_then(Mask::from_rle)
        else {
            continue;
        };
        if (mask.width, mask.height) != (w, h) {
            continue;
        }
        for (px, &on) in map.iter_mut().zip(&mask.data) {
            if on != 0 && *px == 0 {
                *px = (k + 1) as u16;
            }
        }
    }
    map
}

/// The label map as PNG (8-bit up to 255 detections, else 16-bit) with
/// `chunk` (every detection, JSON) in its `sdhop-detections` text chunk.
pub fn label_map_png(resp: &DetectResponse, chunk: String) -> Result<Vec<u8>, png::EncodingError> {
    let map = label_map(resp);
    let wide = resp.detections.len() > 255;
    let mut out = Vec::new();
    let mut enc = png::Encoder::new(
        Cursor::new(&mut out),
        resp.image.width as u32,
        resp.image.height as u32,
    );
    enc.set_color(png::ColorType::Grayscale);
    enc.set_depth(if wide {
        png::BitDepth::Sixteen
    } else {
        png::BitDepth::Eight
    });
    enc.add_itxt_chunk(DETECTIONS_CHUNK.to_string(), chunk)?;
    let mut writer = enc.write_header()?;
    let data: Vec<u8> = if wide {
        map.iter().flat_map(|v| v.to_be_bytes()).collect()
    } else {
        map.iter().map(|&v| v as u8).collect()
    };
    writer.write_image_data(&data)?;
    writer.finish()?;
    Ok(out)
}

fn label_map_response(resp: &DetectResponse) -> Result<Response, ApiError> {
    // The text chunk: every detection, unrounded; the header rounds.
    let full: Vec<HeaderDetection> = resp.detections.iter().map(HeaderDetection::of).collect();
    let dets: Vec<HeaderDetection> = full.iter().map(HeaderDetection::rounded).collect();
    let all = serde_json::to_string(&full).map_err(|e| ApiError::Internal(e.to_string()))?;
    // The header: the best detections whose JSON fits.
    let mut header_json = String::from("[");
    for (i, d) in dets.iter().enumerate() {
        let one =
            ascii_json(&serde_json::to_string(d).map_err(|e| ApiError::Internal(e.to_string()))?);
        if header_json.len() + one.len() + 2 > MAX_DETECTIONS_HEADER {
            break;
        }
        if i > 0 {
            header_json.push(',');
        }
        header_json.push_str(&one);
    }
    header_json.push(']');
    let value = HeaderValue::from_str(&header_json)
        .map_err(|e| ApiError::Internal(format!("X-Detections header: {e}")))?;
    let png =
        label_map_png(resp, all).map_err(|e| ApiError::Internal(format!("PNG encoder: {e}")))?;
    let mut out = ([(header::CONTENT_TYPE, "image/png")], png).into_response();
    let headers = out.headers_mut();
    headers.insert("x-detections", value);
    headers.insert("x-detections-total", HeaderValue::from(dets.len()));
    Ok(out)
}

/// JSON with every non-ASCII character escaped, fit for a header.
fn ascii_json(s: &str) -> String {
    let mut out = String::with_capacity(s.len());
    for c in s.chars() {
        if c.is_ascii() && !c.is_ascii_control() {
            out.push(c);
        } else {
            let mut buf = [0u16; 2];
            for u in c.encode_utf16(&mut buf) {
                out.push_str(&format!("\\u{u:04x}"));
            }
        }
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;

    fn parse(q: &str) -> Result<DetectQuery, ApiError> {
        DetectQuery::parse(Some(q), 100, Duration::from_secs(60))
    }

    #[test]
    fn query_options_parse_and_refuse_bad_values() {
        let q = parse("model=cup,pitcher&model=cup&threshold=-0.5&max_detections=20&masks=both&format=png&timeout_ms=500").unwrap();
        assert_eq!(q.models, vec!["cup", "pitcher"]);
        assert_eq!(q.threshold, Some(-0.5));
        assert_eq!(q.max_detections, Some(20));
        assert_eq!(q.masks, MaskMode::Both);
        assert_eq!(q.format, Some(Format::Png));
        assert_eq!(q.timeout, Some(Duration::from_millis(500)));
        assert_eq!(
            DetectQuery::parse(None, 100, Duration::from_secs(1))
                .unwrap()
                .models
                .len(),
            0
        );
        for bad in [
            "threshold=abc",
            "threshold=NaN",
            "max_detections=0",
            "max_detections=101",
            "max_detections=-1",
            "masks=all",
            "format=gif",
            "timeout_ms=0",
            "timeout_ms=61000",
            "model=",
            "colour=red",
            "threshold=1&threshold=2",
            "masks=raw&masks=raw",
        ] {
            assert!(
                matches!(parse(bad), Err(ApiError::BadRequest(_))),
                "{bad} should be refused"
            );
        }
    }

    #[test]
    fn accept_weights_decide_the_png() {
        let accepts = |v: &str| {
            let mut h = HeaderMap::new();
            h.insert(header::ACCEPT, HeaderValue::from_str(v).unwrap());
            matches!(negotiate(&h, None), Ok(Format::Png))
        };
        assert!(accepts("image/png"));
        assert!(accepts("image/png, application/json;q=0.5"));
        assert!(accepts("IMAGE/PNG ; q=0.9, */*;q=0.1"));
        assert!(!accepts("image/png;q=0"));
        assert!(!accepts("image/png;q=0.5, application/json"));
        assert!(!accepts("application/json, image/png;q=0.2"));
        assert!(!accepts("*/*"));
        assert!(!accepts("image/png;q=0.5, */*"));
    }

    #[test]
    fn non_ascii_is_escaped_for_headers() {
        assert_eq!(ascii_json("{\"l\":\"tasse\"}"), "{\"l\":\"tasse\"}");
        assert_eq!(ascii_json("é"), "\\u00e9");
        assert!(HeaderValue::from_str(&ascii_json("\"🍵\"")).is_ok());
    }

    fn with_accept(values: &[&str]) -> HeaderMap {
        let mut h = HeaderMap::new();
        for v in values {
            h.append(header::ACCEPT, HeaderValue::from_str(v).unwrap());
        }
        h
    }

    #[test]
    fn accept_is_negotiated_as_http_says() {
        use Format::{Json, Png};
        let cases: [(&[&str], Option<Format>, Option<Format>); 16] = [
            (&[], None, Some(Json)),
            (&["image/*"], None, Some(Png)),
            (&["application/json;q=0.9, image/*;q=1"], None, Some(Png)),
            (&["image/png, application/json"], None, Some(Json)),
            (&["*/*"], None, Some(Json)),
            (&["image/png;q=0.5, */*;q=0.1"], None, Some(Png)),
            // A malformed weight leaves its range out: none is left.
            (&["image/png;q=abc"], None, Some(Json)),
            (&["image/png;q=1.5"], None, Some(Json)),
            (
                &["image/png;q=0.0001, application/json;q=0.5"],
                None,
                Some(Json),
            ),
            // Both refused, or neither listed: 406.
            (&["image/png;q=0, application/json;q=0"], None, None),
            (&["text/html"], None, None),
            (&["image/png;q=0"], None, None),
            // format= chooses among acceptable types, never a refused one.
            (&["image/png;q=0, application/json"], Some(Png), None),
            (&["application/json"], Some(Png), None),
            (&["image/png;q=0.1, application/json"], Some(Png), Some(Png)),
            // Two Accept headers count as one list.
            (&["application/json;q=0", "image/png"], None, Some(Png)),
        ];
        for (accept, asked, want) in cases {
            let got = negotiate(&with_accept(accept), asked);
            match (got, want) {
                (Ok(f), Some(w)) => assert_eq!(f, w, "{accept:?} {asked:?}"),
                (Err(ApiError::NotAcceptable(m)), None) => assert!(!m.contains('\n')),
                (got, want) => panic!("{accept:?} {asked:?}: {got:?}, expected {want:?}"),
            }
        }
    }

    #[test]
    fn label_maps_refuse_options_they_cannot_honour() {
        for (q, ok) in [
            ("format=png", true),
            ("format=png&masks=raw", true),
            ("format=png&masks=none", false),
            ("format=png&masks=both", false),
            ("format=png&rle=compressed", false),
            ("format=json&masks=none&rle=compressed", true),
        ] {
            let query = parse(q).unwrap();
            let format = query.format.unwrap();
            let r = check_format_options(format, &query);
            assert_eq!(r.is_ok(), ok, "{q}: {r:?}");
            if let Err(e) = r {
                assert!(matches!(e, ApiError::Unprocessable(_)), "{q}");
            }
        }
    }
}
