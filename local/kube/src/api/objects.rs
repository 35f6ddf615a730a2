//! Shared read paths for stored kinds: list (selectors, paging, tables), get, and list items in
//! the real wire form.

use axum::extract::{Path, Query, State};
use axum::http::{header, HeaderMap, StatusCode};
use axum::response::{IntoResponse, Response};
use serde_json::{json, Map, Value};

use super::table::{wants_table, Tabular};
use super::watch::watch;
use super::{int_param, json, truthy, AppState, Params};
use crate::selector::{FieldSelector, LabelSelector};
use crate::status::ApiError;
use crate::store::{ObjKey, Stored};

/// The object as JSON (with apiVersion and kind).
pub fn to_json<T: Stored>(obj: &T) -> Value {
    serde_json::to_value(obj).unwrap_or_default()
}

/// A list item: real servers omit apiVersion and kind inside lists.
fn item_json<T: Stored>(obj: &T) -> Value {
    as_list_item(to_json(obj))
}

/// `v` without apiVersion and kind, as a list carries its items.
pub fn as_list_item(mut v: Value) -> Value {
    if let Value::Object(m) = &mut v {
        m.remove("apiVersion");
        m.remove("kind");
    }
    v
}

/// Parsed selectors of a request.
pub struct Selectors {
    /// Label selector.
    pub labels: LabelSelector,
    /// Field selector.
    pub fields: FieldSelector,
}

impl Selectors {
    /// Parses `labelSelector` and `fieldSelector` (400 on errors).
    pub fn parse<T: Stored>(p: &Params) -> Result<Self, ApiError> {
        let labels = LabelSelector::parse(p.label_selector.as_deref().unwrap_or_default())
            .map_err(ApiError::bad_request)?;
        let fields =
            FieldSelector::parse(p.field_selector.as_deref().unwrap_or_default(), T::FIELDS)
                .map_err(ApiError::bad_request)?;
        Ok(Self { labels, fields })
    }

    /// Whether the object passes both selectors.
    pub fn matches<T: Stored>(&self, obj: &T) -> bool {
        self.labels.matches(obj.meta().labels.as_ref()) && self.fields.matches(|f| obj.field(f))
    }
}

fn encode_continue(key: &ObjKey) -> String {
    format!("{}/{}", key.namespace, key.name)
        .bytes()
        .map(|b| format!("{b:02x}"))
        .collect()
}

fn decode_continue(token: &str) -> Result<ObjKey, ApiError> {
    let bad = || ApiError::bad_request(format!("continue key is not valid: {token:?}"));
    if token.len() % 2 != 0 {
        return Err(bad());
    }
    let bytes: Result<Vec<u8>, _> = (0..token.len())
        .step_by(2)
        .map(|i| u8::from_str_radix(&token[i..i + 2], 16))
        .collect();
    let text = String::from_utf8(bytes.map_err(|_| bad())?).map_err(|_| bad())?;
    let (ns, name) = text.split_once('/').ok_or_else(bad)?;
    Ok(ObjKey::new(ns, name))
}

/// GET on a collection: a watch, a Table, or a `<Kind>List`.
pub async fn list<T: Stored + Tabular>(
    state: &AppState,
    headers: &HeaderMap,
    namespace: Option<&str>,
    p: Params,
) -> Result<Response, ApiError> {
    if let Some(ns) = namespace {
        state.check("list", &T::RESOURCE, ns, None)?;
    }
    let sel = Selectors::parse::<T>(&p)?;
    if truthy(&p.watch) {
        return watch::<T>(state, namespace, &p, sel);
    }
    let limit = int_param("limit", &p.limit)?.filter(|l| *l > 0);
    let after = p
        .continue_
        .as_deref()
        .filter(|c| !c.is_empty())
        .map(decode_continue)
        .transpose()?;
    let forbidden = &state.forbidden;
    let (mut items, rv) = state.rt.store.list::<T>(namespace, |o| {
        sel.matches(o) && !forbidden.contains(o.meta().namespace.as_deref().unwrap_or_default())
    });
    if let Some(after) = &after {
        items.retain(|o| ObjKey::of(o.meta()) > *after);
    }
    let mut meta = Map::new();
    meta.insert("resourceVersion".into(), json!(rv.to_string()));
    if let Some(limit) = limit.map(|l| l as usize).filter(|l| items.len() > *l) {
        let remaining = items.len() - limit;
        items.truncate(limit);
        if let Some(last) = items.last() {
            meta.insert(
                "continue".into(),
                json!(encode_continue(&ObjKey::of(last.meta()))),
            );
            meta.insert("remainingItemCount".into(), json!(remaining));
        }
    }
    if wants_table(headers) {
        return Ok(json(StatusCode::OK, &T::table(&items, Value::Object(meta))));
    }
    let res = T::RESOURCE;
    let body = json!({
        "kind": format!("{}List", res.kind),
        "apiVersion": res.api_version(),
        "metadata": meta,
        "items": items.iter().map(item_json).collect::<Vec<_>>(),
    });
    Ok(json(StatusCode::OK, &body))
}

/// GET on one object (404 Status when missing).
pub fn get_one<T: Stored + Tabular>(
    state: &AppState,
    headers: &HeaderMap,
    ns: &str,
    name: &str,
) -> Result<Response, ApiError> {
    state.check("get", &T::RESOURCE, ns, Some(name))?;
    let obj = state
        .rt
        .store
        .get::<T>(&ObjKey::new(ns, name))
        .ok_or_else(|| ApiError::not_found(&T::RESOURCE, name))?;
    if wants_table(headers) {
        let rv = obj.meta().resource_version.clone().unwrap_or_default();
        return Ok(json(
            StatusCode::OK,
            &T::table(std::slice::from_ref(&obj), json!({ "resourceVersion": rv })),
        ));
    }
    Ok(json(StatusCode::OK, &to_json(&obj)))
}

/// A plain-text response.
pub fn text(body: Vec<u8>) -> Response {
    let mut resp = (StatusCode::OK, body).into_response();
    resp.headers_mut().insert(
        header::CONTENT_TYPE,
        header::HeaderValue::from_static("text/plain"),
    );
    resp
}

/// A handler's result as a response (errors as `Status` objects).
pub fn into_response(r: Result<Response, ApiError>) -> Response {
    r.unwrap_or_else(IntoResponse::into_response)
}

/// GET `.../namespaces/{ns}/<resource>`, for every resource kind.
pub async fn list_in<T: Stored + Tabular>(
    State(state): State<AppState>,
    Path(ns): Path<String>,
    headers: HeaderMap,
    Query(p): Query<Params>,
) -> Response {
    into_response(list::<T>(&state, &headers, Some(&ns), p).await)
}

/// GET `.../<resource>` across namespaces.
pub async fn list_everywhere<T: Stored + Tabular>(
    State(state): State<AppState>,
    headers: HeaderMap,
    Query(p): Query<Params>,
) -> Response {
    into_response(list::<T>(&state, &headers, None, p).await)
}

/// GET `.../namespaces/{ns}/<resource>/{name}`.
pub async fn get_named<T: Stored + Tabular>(
    State(state): State<AppState>,
    Path((ns, name)): Path<(String, String)>,
    headers: HeaderMap,
) -> Response {
    into_response(get_one::<T>(&state, &headers, &ns, &name))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn continue_tokens_round_trip() {
        let k = ObjKey::new("ns", "job-1");
        assert_eq!(decode_continue(&encode_continue(&k)).unwrap(), k);
        assert!(decode_continue("zz").is_err());
    }
}
