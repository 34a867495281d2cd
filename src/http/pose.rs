//! `POST /pose`: a `multipart/form-data` body with the parts `image` (JPEG
//! or PNG), `mesh` (OBJ or PLY), optional `mask` (PNG, non-zero pixels are
//! visible) and `params` (JSON, [`PoseParams`]); answers the refined pose
//! ([`crate::pose::api::PoseResponse`]). Admission, deadlines and errors
//! follow `/detect`: 400 malformed body or query, 404 unknown model, 413
//! too large, 415 not multipart, 422 a mesh, mask, image or parameters
//! that cannot be used, 503 overloaded or late.

use std::sync::Arc;
use std::time::{Duration, Instant};

use axum::body::Bytes;
use axum::extract::{FromRequest, Multipart, RawQuery, Request, State};
use axum::response::{IntoResponse, Response};
use axum::Json;

use super::detect::{before_body, media_in, multipart_error, timeout_param};
use super::error::ApiError;
use super::image::{decode, decode_mask, image_size, mask_size};
use super::state::AppState;
use crate::infer::{Lane, PoseTask};
use crate::pose::api::{MaskSource, PoseParams};
use crate::pose::Mesh;
use crate::vision::Deadline;

/// The parts of a pose request, as sent (views of the buffered body: no
/// copies).
#[derive(Default)]
struct Parts {
    image: Option<Bytes>,
    mesh: Option<Bytes>,
    mask: Option<Bytes>,
    params: Option<Bytes>,
}

/// The least `timeout_ms` of a pose: no pose is refined faster (the
/// median is some 150 ms through the service), and a shorter deadline
/// would not cover the multipart upload itself.
pub const MIN_POSE_TIMEOUT: Duration = Duration::from_millis(100);

/// The query of `POST /pose`: only `timeout_ms`, at most once.
fn parse_query(raw: Option<&str>, max_timeout: Duration) -> Result<Option<Duration>, ApiError> {
    let mut timeout = None;
    for (k, v) in form_urlencoded::parse(raw.unwrap_or("").as_bytes()) {
        match k.as_ref() {
            "timeout_ms" if timeout.is_some() => {
                return Err(ApiError::BadRequest(
                    "query parameter timeout_ms is repeated: give it once".into(),
                ))
            }
            "timeout_ms" => timeout = Some(timeout_param(&v, MIN_POSE_TIMEOUT, max_timeout)?),
            _ => {
                return Err(ApiError::BadRequest(format!(
                    "query parameter {}: unknown parameter (POST /pose takes only timeout_ms)",
                    super::error::shorten(&k)
                )))
            }
        }
    }
    Ok(timeout)
}

/// Reads the multipart body within the route's body limit; unknown or
/// repeated parts are refused.
async fn read_parts(req: Request, limit: usize) -> Result<Parts, ApiError> {
    let mut mp = Multipart::from_request(req, &())
        .await
        .map_err(|e| ApiError::BadRequest(e.body_text()))?;
    let mut parts = Parts::default();
    // The body is already in memory (see `body::buffer`), so the first
    // unknown or repeated part is answered at once: a body of a million
    // empty parts costs no more than its first wrong one (it took 0.8 s
    // of the runtime's thread, past a 300 ms deadline).
    while let Some(field) = mp
        .next_field()
        .await
        .map_err(|e| multipart_error(&e, limit))?
    {
        let name = field.name().unwrap_or_default().to_string();
        let slot = match name.as_str() {
            "image" => &mut parts.image,
            "mesh" => &mut parts.mesh,
            "mask" => &mut parts.mask,
            "params" => &mut parts.params,
            _ => {
                return Err(ApiError::BadRequest(format!(
                    "unknown part {}: expected image, mesh, mask and params",
                    super::error::shorten(&name)
                )))
            }
        };
        if slot.is_some() {
            return Err(ApiError::BadRequest(format!(
                "the part {name:?} is repeated"
            )));
        }
        let bytes = field
            .bytes()
            .await
            .map_err(|e| multipart_error(&e, limit))?;
        *slot = Some(bytes);
    }
    Ok(parts)
}

/// The `params` part: 400 when it is not JSON, 422 when it is JSON of the
/// wrong shape.
fn parse_params(bytes: &[u8]) -> Result<PoseParams, ApiError> {
    serde_json::from_slice(bytes).map_err(|e| {
        let msg = format!("params: {e}");
        if e.is_data() {
            ApiError::Unprocessable(msg)
        } else {
            ApiError::BadRequest(msg)
        }
    })
}

/// `POST /pose`.
pub async fn pose(
    State(state): State<Arc<AppState>>,
    RawQuery(raw): RawQuery,
    req: Request,
) -> Result<Response, ApiError> {
    let arrived = Instant::now();
    let cfg = state.config;
    // The query first only for its deadline (see /detect).
    let timeout = parse_query(raw.as_deref(), cfg.max_timeout);
    let deadline = arrived
        + timeout
            .as_ref()
            .ok()
            .copied()
            .flatten()
            .unwrap_or(cfg.default_timeout);
    let media = media_in(
        req.headers(),
        &["multipart/form-data"],
        "multipart/form-data with the parts image, mesh, params and optionally mask",
    );
    let pacing = state.pacing(deadline);
    let limit = cfg.max_pose_body_bytes;
    let req = match super::body::buffer(req, limit, &pacing, state.infer.grace_ended()).await {
        Ok(req) => req,
        Err(e @ ApiError::RequestTimeout(_)) => return Err(before_body(e, timeout, media)),
        Err(e) => return Err(e),
    };
    timeout?;
    // Admission to the pose lane before keeping anything, as for /detect.
    let permit = state.infer.admit_to(Lane::Pose)?;
    media?;
    let parts = read_parts(req, cfg.max_pose_body_bytes).await?;
    let missing =
        |name: &str| ApiError::BadRequest(format!("the multipart body has no `{name}` part"));
    let image = parts.image.ok_or_else(|| missing("image"))?;
    let mesh = parts.mesh.ok_or_else(|| missing("mesh"))?;
    let params = parse_params(&parts.params.ok_or_else(|| missing("params"))?)?;
    let limits = cfg.image;
    // The cheap checks first, from the headers alone: the sizes of the
    // image and the mask, the parameters, the model and its labels.
    let size = image_size(&image, &limits)?;
    let mask_bytes = parts.mask;
    let mask_dims = mask_bytes
        .as_ref()
        .map(|b| mask_size(b, &limits))
        .transpose()?;
    params.check(size, mask_dims)?;
    // A detection is needed for its mask, or for the start poses when
    // there is no initial pose.
    let needs_detection = params.mask == Some(MaskSource::Detect) || params.initial_pose.is_none();
    let model = match (needs_detection, &params.model) {
        (true, Some(name)) => {
            let loaded = state
                .model(name)
                .ok_or_else(|| ApiError::UnknownModel(name.clone()))?;
            params.check_model(&loaded.model)?;
            Some(Arc::clone(&loaded.model))
        }
        _ => None,
    };
    // The memory of its image and its detection, reserved before either
    // is decoded (the mesh is bounded by its own limits).
    let detector: Vec<&crate::model::Model> = model.iter().map(|m| m.as_ref()).collect();
    let cost = Some(
        state
            .infer
            .reserve(size.0, size.1, &detector, deadline)
            .await?,
    );
    let mesh_limits = cfg.mesh;
    // On the pose pool, at its priority: what the client sent costs what
    // its bytes allow, and that is pose work.
    let (task, dropped) = state
        .infer
        .on_pose_pool(deadline, move || {
            // The mesh first: its reading is bounded by its bytes and the
            // limits before any allocation, and by the deadline.
            let (mesh, dropped) = Mesh::read_within(&mesh, &mesh_limits, &Deadline::at(deadline))?;
            let image = decode(&image, &limits)?;
            let mask = mask_bytes
                .map(|b| decode_mask(&b, &limits, Some(size)))
                .transpose()?;
            params.check_projection(&mesh, size)?;
            let task = PoseTask {
                image: Arc::new(image),
                mesh,
                params,
                mask,
                model,
                cost,
            };
            Ok::<_, ApiError>((task, dropped))
        })
        .await??;
    let mut resp = state.infer.pose(permit, task, deadline).await?;
    resp.mesh_faces_dropped = dropped.total();
    Ok(Json(resp).into_response())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn params_syntax_is_400_and_shape_is_422() {
        assert!(matches!(
            parse_params(b"{\"intrinsics\":"),
            Err(ApiError::BadRequest(_))
        ));
        assert!(matches!(
            parse_params(b"{\"intrinsics\": 3}"),
            Err(ApiError::Unprocessable(_))
        ));
        let ok = br#"{"intrinsics":{"fx":500,"fy":500,"cx":320,"cy":240},
            "initial_pose":{"rotation":[[1,0,0],[0,1,0],[0,0,1]],"translation":[0,0,0.5]}}"#;
        assert!(parse_params(ok).is_ok());
    }

    #[test]
    fn only_timeout_is_a_query_parameter() {
        let max = Duration::from_secs(10);
        assert_eq!(
            parse_query(Some("timeout_ms=250"), max).unwrap(),
            Some(Duration::from_millis(250))
        );
        assert_eq!(parse_query(None, max).unwrap(), None);
        for bad in [
            "timeout_ms=0",
            "timeout_ms=99",
            "timeout_ms=x",
            "timeout_ms=20000",
            "model=cup",
            "timeout_ms=100&timeout_ms=200",
        ] {
            assert!(
                matches!(parse_query(Some(bad), max), Err(ApiError::BadRequest(_))),
                "{bad}"
            );
        }
    }
}
