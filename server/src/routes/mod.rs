//! Every route of the server, declared in one place. The OpenAPI document is collected from the
//! same declarations, so it cannot miss a route.

mod common;
mod contract;
mod contributions;
mod extract;
mod maps;
mod ops;

use crate::state::SharedState;
use axum::Router;
use axum::extract::DefaultBodyLimit;
use utoipa::OpenApi;
use utoipa_axum::router::OpenApiRouter;
use utoipa_axum::routes;
use utoipa_swagger_ui::SwaggerUi;

pub use extract::parse_json;

#[derive(OpenApi)]
#[openapi(
    info(
        title = "echomap map server",
        description = "Versioned crowd-sourced prior maps for cooperative Channel-SLAM. Errors are \
                       application/problem+json (RFC 9457); writes need `Authorization: Bearer <token>`."
    ),
    components(schemas(crate::error::Problem)),
    tags((name = "maps"), (name = "contributions"), (name = "operations"))
)]
struct ApiDoc;

/// The router and its OpenAPI document.
pub fn api(state: SharedState) -> (Router, serde_json::Value) {
    let limit = state.config.body_limit;
    let (router, doc) = OpenApiRouter::with_openapi(ApiDoc::openapi())
        .routes(routes!(ops::healthz))
        .routes(routes!(ops::readyz))
        .routes(routes!(ops::metrics))
        .routes(routes!(maps::list_maps))
        .routes(routes!(maps::get_map, maps::put_map))
        .routes(routes!(maps::get_version))
        .routes(routes!(maps::match_map))
        .routes(routes!(
            contributions::list_contributions,
            contributions::post_contribution
        ))
        .routes(routes!(contributions::delete_contribution))
        .split_for_parts();
    let doc = contract::tighten(doc);
    let router = router
        .route_layer(axum::middleware::from_fn(crate::metrics::track))
        .layer(DefaultBodyLimit::max(limit))
        .layer(axum::Extension(extract::Limit(limit)))
        .with_state(state);
    (router, doc)
}

/// The whole application: API routes, `/openapi.json`, the API docs page at `/docs` (Swagger
/// UI) and the map viewer at `/viewer/` (`/` leads there); assets embedded in the binary.
pub fn app(state: SharedState) -> Router {
    let (router, doc) = api(state);
    router
        .merge(SwaggerUi::new("/docs").external_url_unchecked("/openapi.json", doc))
        .route("/", axum::routing::get(crate::viewer::to_page))
        .route("/viewer", axum::routing::get(crate::viewer::to_page))
        .route("/viewer/", axum::routing::get(crate::viewer::page))
        .fallback(ops::not_found)
}
