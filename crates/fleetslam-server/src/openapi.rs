//! The OpenAPI document, generated from the handlers' annotations, at `/v1/openapi.json`.

use axum::Json;
use utoipa::OpenApi;

#[derive(OpenApi)]
#[openapi(
    info(
        title = "fleetslam",
        description = "Multi-robot FastSLAM server: robots post odometry and observations; one \
                       coordinator per run merges them into a shared map."
    ),
    paths(
        crate::app::healthz,
        crate::metrics::metrics,
        crate::app::create_run,
        crate::app::list_runs,
        crate::app::get_run,
        crate::app::end_run,
        crate::app::register_robot,
        crate::app::post_observations,
        crate::app::live,
        crate::api_history::get_state,
        crate::api_history::timeline,
        crate::api_history::series,
        crate::api_history::trajectories,
        crate::api_history::put_truth,
        crate::api_history::get_truth,
        crate::api_history::evaluation,
        crate::api_history::export,
        crate::api_history::rerun,
        crate::api_history::delete_run,
        crate::api_history::list_models,
    ),
    components(schemas(
        crate::error::ErrorBody,
        crate::coordinator::RunState,
        crate::coordinator::RobotStatus,
        crate::coordinator::LandmarkState,
        crate::coordinator::RecordAck,
    )),
    tags(
        (name = "runs", description = "Runs: create, list, state, history, export"),
        (name = "robots", description = "Robots: register, post observations"),
        (name = "server", description = "Health and metrics"),
    )
)]
#[derive(Debug)]
pub struct ApiDoc;

/// `GET /v1/openapi.json`
pub async fn openapi() -> Json<utoipa::openapi::OpenApi> {
    Json(ApiDoc::openapi())
}
