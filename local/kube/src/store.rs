//! The object store: Jobs and Pods by namespace and name, one increasing resourceVersion, watch events.

use std::collections::{BTreeMap, VecDeque};
use std::sync::{Arc, Mutex, MutexGuard};

use k8s_openapi::api::batch::v1::Job;
use k8s_openapi::api::core::v1::Pod;
use k8s_openapi::apimachinery::pkg::apis::meta::v1::ObjectMeta;
use serde::Serialize;
use tokio::sync::broadcast;

use crate::status::{ApiError, Resource, JOBS, PODS};

/// How many past events a watch can resume from.
const HISTORY: usize = 4096;

/// Namespace and name of an object.
#[derive(Clone, Debug, PartialEq, Eq, PartialOrd, Ord, Hash)]
pub struct ObjKey {
    /// Namespace.
    pub namespace: String,
    /// Name.
    pub name: String,
}

impl ObjKey {
    /// A key from borrowed parts.
    pub fn new(namespace: &str, name: &str) -> Self {
        Self {
            namespace: namespace.to_owned(),
            name: name.to_owned(),
        }
    }

    /// The key of an object's metadata.
    pub fn of(meta: &ObjectMeta) -> Self {
        Self::new(
            meta.namespace.as_deref().unwrap_or_default(),
            meta.name.as_deref().unwrap_or_default(),
        )
    }
}

/// A stored kind: Jobs or Pods.
pub trait Stored: Clone + PartialEq + Serialize + Send + Sync + 'static {
    /// The resource, for messages.
    const RESOURCE: Resource;
    /// Metadata.
    fn meta(&self) -> &ObjectMeta;
    /// Metadata, mutable.
    fn meta_mut(&mut self) -> &mut ObjectMeta;
    /// Value of a selectable field (`metadata.name`, `status.phase`, ...).
    fn field(&self, field: &str) -> String;
    /// The fields a field selector may use.
    const FIELDS: &'static [&'static str];
    /// The table in the store.
    fn table_mut(inner: &mut Inner) -> &mut BTreeMap<ObjKey, Self>;
    /// Wraps into the event enum.
    fn wrap(self) -> AnyObject;
}

/// A stored object of either kind.
#[derive(Clone, Debug)]
pub enum AnyObject {
    /// A Job.
    Job(Box<Job>),
    /// A Pod.
    Pod(Box<Pod>),
}

impl AnyObject {
    /// Metadata.
    pub fn meta(&self) -> &ObjectMeta {
        match self {
            Self::Job(j) => &j.metadata,
            Self::Pod(p) => &p.metadata,
        }
    }

    /// The resource.
    pub fn resource(&self) -> Resource {
        match self {
            Self::Job(_) => JOBS,
            Self::Pod(_) => PODS,
        }
    }

    /// JSON with apiVersion and kind, as watch events carry it.
    pub fn to_json(&self) -> serde_json::Value {
        match self {
            Self::Job(j) => serde_json::to_value(j.as_ref()),
            Self::Pod(p) => serde_json::to_value(p.as_ref()),
        }
        .unwrap_or_default()
    }

    /// A selectable field.
    pub fn field(&self, field: &str) -> String {
        match self {
            Self::Job(j) => j.field(field),
            Self::Pod(p) => p.field(field),
        }
    }
}

/// Watch event type.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum EventType {
    /// `ADDED`.
    Added,
    /// `MODIFIED`.
    Modified,
    /// `DELETED`.
    Deleted,
}

impl EventType {
    /// The wire name.
    pub fn as_str(self) -> &'static str {
        match self {
            Self::Added => "ADDED",
            Self::Modified => "MODIFIED",
            Self::Deleted => "DELETED",
        }
    }
}

/// One change, as watches stream it.
#[derive(Clone, Debug)]
pub struct Event {
    /// What happened.
    pub type_: EventType,
    /// The resourceVersion of this change.
    pub rv: u64,
    /// The object after the change (before removal for `DELETED`).
    pub object: AnyObject,
}

/// Past events and a receiver of later ones.
pub struct Subscription {
    /// Kept events after the requested version.
    pub past: Vec<Arc<Event>>,
    /// Later events.
    pub live: broadcast::Receiver<Arc<Event>>,
    /// The store's version when subscribing.
    pub rv: u64,
}

/// Store contents.
#[derive(Default)]
pub struct Inner {
    rv: u64,
    jobs: BTreeMap<ObjKey, Job>,
    pods: BTreeMap<ObjKey, Pod>,
    history: VecDeque<Arc<Event>>,
}

/// The store shared by the API and the runtime.
pub struct Store {
    inner: Mutex<Inner>,
    events: broadcast::Sender<Arc<Event>>,
}

impl Default for Store {
    fn default() -> Self {
        Self::new()
    }
}

fn now() -> k8s_openapi::apimachinery::pkg::apis::meta::v1::Time {
    let since = std::time::SystemTime::now()
        .duration_since(std::time::UNIX_EPOCH)
        .unwrap_or_default();
    let ts = k8s_openapi::jiff::Timestamp::new(since.as_secs() as i64, since.subsec_nanos() as i32)
        .unwrap_or(k8s_openapi::jiff::Timestamp::UNIX_EPOCH);
    k8s_openapi::apimachinery::pkg::apis::meta::v1::Time(ts)
}

/// The current time as the API writes it.
pub fn time_now() -> k8s_openapi::apimachinery::pkg::apis::meta::v1::Time {
    now()
}

impl Store {
    /// An empty store.
    pub fn new() -> Self {
        let (events, _) = broadcast::channel(1024);
        Self {
            inner: Mutex::new(Inner::default()),
            events,
        }
    }

    fn lock(&self) -> MutexGuard<'_, Inner> {
        // NB: a panic while holding the lock leaves consistent data (every write is one insert).
        self.inner.lock().unwrap_or_else(|e| e.into_inner())
    }

    fn emit(&self, inner: &mut Inner, type_: EventType, object: AnyObject) {
        let event = Arc::new(Event {
            type_,
            rv: inner.rv,
            object,
        });
        inner.history.push_back(event.clone());
        while inner.history.len() > HISTORY {
            inner.history.pop_front();
        }
        // NB: no receivers is fine; watches subscribe on demand.
        let _ = self.events.send(event);
    }

    /// The latest resourceVersion.
    pub fn resource_version(&self) -> u64 {
        self.lock().rv
    }

    /// Inserts a new object, stamping its resourceVersion. 409 if the name is taken.
    pub fn create<T: Stored>(&self, mut obj: T) -> Result<T, ApiError> {
        let key = ObjKey::of(obj.meta());
        let mut inner = self.lock();
        if T::table_mut(&mut inner).contains_key(&key) {
            return Err(ApiError::already_exists(&T::RESOURCE, &key.name));
        }
        inner.rv += 1;
        obj.meta_mut().resource_version = Some(inner.rv.to_string());
        T::table_mut(&mut inner).insert(key, obj.clone());
        self.emit(&mut inner, EventType::Added, obj.clone().wrap());
        Ok(obj)
    }

    /// The object, if stored.
    pub fn get<T: Stored>(&self, key: &ObjKey) -> Option<T> {
        T::table_mut(&mut self.lock()).get(key).cloned()
    }

    /// Objects (of one namespace, or all) that pass `keep`, ordered by namespace and name,
    /// with the store's resourceVersion.
    pub fn list<T: Stored>(
        &self,
        namespace: Option<&str>,
        keep: impl Fn(&T) -> bool,
    ) -> (Vec<T>, u64) {
        let mut inner = self.lock();
        let rv = inner.rv;
        let items = T::table_mut(&mut inner)
            .iter()
            .filter(|(k, _)| namespace.is_none_or(|ns| k.namespace == ns))
            .filter(|(_, v)| keep(v))
            .map(|(_, v)| v.clone())
            .collect();
        (items, rv)
    }

    /// Applies `f` to the stored object; a real change gets a new resourceVersion and an event.
    pub fn update<T: Stored>(&self, key: &ObjKey, f: impl FnOnce(&mut T)) -> Option<T> {
        let mut inner = self.lock();
        let current = T::table_mut(&mut inner).get(key)?.clone();
        let mut next = current.clone();
        f(&mut next);
        if next == current {
            return Some(current);
        }
        inner.rv += 1;
        next.meta_mut().resource_version = Some(inner.rv.to_string());
        T::table_mut(&mut inner).insert(key.clone(), next.clone());
        self.emit(&mut inner, EventType::Modified, next.clone().wrap());
        Some(next)
    }

    /// Removes the object.
    pub fn remove<T: Stored>(&self, key: &ObjKey) -> Option<T> {
        let mut inner = self.lock();
        let mut obj = T::table_mut(&mut inner).remove(key)?;
        inner.rv += 1;
        obj.meta_mut().resource_version = Some(inner.rv.to_string());
        self.emit(&mut inner, EventType::Deleted, obj.clone().wrap());
        Some(obj)
    }

    /// Every namespace that holds an object.
    pub fn namespaces(&self) -> Vec<String> {
        let inner = self.lock();
        let mut out: Vec<String> = inner
            .jobs
            .keys()
            .chain(inner.pods.keys())
            .map(|k| k.namespace.clone())
            .collect();
        out.sort();
        out.dedup();
        out
    }

    /// Events after `since` and a receiver for later ones, with no gap between them.
    /// `Err` carries the oldest resourceVersion still kept when `since` is older.
    pub fn subscribe(&self, since: u64) -> Result<Subscription, u64> {
        let inner = self.lock();
        let oldest = inner.history.front().map(|e| e.rv).unwrap_or(inner.rv + 1);
        if since + 1 < oldest && since < inner.rv {
            return Err(oldest);
        }
        let past = inner
            .history
            .iter()
            .filter(|e| e.rv > since)
            .cloned()
            .collect();
        Ok(Subscription {
            past,
            live: self.events.subscribe(),
            rv: inner.rv,
        })
    }

    /// A receiver of every later event, with the current resourceVersion and the matching objects
    /// of both kinds (for a watch that starts with synthetic ADDED events).
    pub fn snapshot_and_subscribe(
        &self,
        resource: &Resource,
        namespace: Option<&str>,
    ) -> (Vec<AnyObject>, broadcast::Receiver<Arc<Event>>, u64) {
        let inner = self.lock();
        let in_ns = |k: &ObjKey| namespace.is_none_or(|ns| k.namespace == ns);
        let objects: Vec<AnyObject> = if *resource == JOBS {
            inner
                .jobs
                .iter()
                .filter(|(k, _)| in_ns(k))
                .map(|(_, j)| AnyObject::Job(Box::new(j.clone())))
                .collect()
        } else {
            inner
                .pods
                .iter()
                .filter(|(k, _)| in_ns(k))
                .map(|(_, p)| AnyObject::Pod(Box::new(p.clone())))
                .collect()
        };
        (objects, self.events.subscribe(), inner.rv)
    }
}

impl Stored for Job {
    const RESOURCE: Resource = JOBS;
    const FIELDS: &'static [&'static str] =
        &["metadata.name", "metadata.namespace", "status.successful"];

    fn meta(&self) -> &ObjectMeta {
        &self.metadata
    }

    fn meta_mut(&mut self) -> &mut ObjectMeta {
        &mut self.metadata
    }

    fn field(&self, field: &str) -> String {
        match field {
            "metadata.name" => self.metadata.name.clone().unwrap_or_default(),
            "metadata.namespace" => self.metadata.namespace.clone().unwrap_or_default(),
            "status.successful" => self
                .status
                .as_ref()
                .and_then(|s| s.succeeded)
                .unwrap_or(0)
                .to_string(),
            _ => String::new(),
        }
    }

    fn table_mut(inner: &mut Inner) -> &mut BTreeMap<ObjKey, Self> {
        &mut inner.jobs
    }

    fn wrap(self) -> AnyObject {
        AnyObject::Job(Box::new(self))
    }
}

impl Stored for Pod {
    const RESOURCE: Resource = PODS;
    const FIELDS: &'static [&'static str] = &[
        "metadata.name",
        "metadata.namespace",
        "spec.nodeName",
        "spec.restartPolicy",
        "spec.schedulerName",
        "spec.serviceAccountName",
        "status.phase",
        "status.podIP",
        "status.nominatedNodeName",
    ];

    fn meta(&self) -> &ObjectMeta {
        &self.metadata
    }

    fn meta_mut(&mut self) -> &mut ObjectMeta {
        &mut self.metadata
    }

    fn field(&self, field: &str) -> String {
        let spec = self.spec.as_ref();
        let status = self.status.as_ref();
        let s = match field {
            "metadata.name" => self.metadata.name.clone(),
            "metadata.namespace" => self.metadata.namespace.clone(),
            "spec.nodeName" => spec.and_then(|s| s.node_name.clone()),
            "spec.restartPolicy" => spec.and_then(|s| s.restart_policy.clone()),
            "spec.schedulerName" => spec.and_then(|s| s.scheduler_name.clone()),
            "spec.serviceAccountName" => spec.and_then(|s| s.service_account_name.clone()),
            "status.phase" => status.and_then(|s| s.phase.clone()),
            "status.podIP" => status.and_then(|s| s.pod_ip.clone()),
            "status.nominatedNodeName" => status.and_then(|s| s.nominated_node_name.clone()),
            _ => None,
        };
        s.unwrap_or_default()
    }

    fn table_mut(inner: &mut Inner) -> &mut BTreeMap<ObjKey, Self> {
        &mut inner.pods
    }

    fn wrap(self) -> AnyObject {
        AnyObject::Pod(Box::new(self))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn job(ns: &str, name: &str) -> Job {
        Job {
            metadata: ObjectMeta {
                namespace: Some(ns.into()),
                name: Some(name.into()),
                ..Default::default()
            },
            ..Default::default()
        }
    }

    #[test]
    fn resource_versions_increase_and_unchanged_updates_keep_them() {
        let store = Store::new();
        let a = store.create(job("default", "a")).unwrap();
        let b = store.create(job("default", "b")).unwrap();
        let rv = |j: &Job| {
            j.metadata
                .resource_version
                .clone()
                .unwrap()
                .parse::<u64>()
                .unwrap()
        };
        assert!(rv(&b) > rv(&a));
        let key = ObjKey::new("default", "a");
        let same = store.update::<Job>(&key, |_| {}).unwrap();
        assert_eq!(rv(&same), rv(&a));
        let changed = store
            .update::<Job>(&key, |j| {
                j.metadata.labels = Some([("x".into(), "1".into())].into())
            })
            .unwrap();
        assert!(rv(&changed) > rv(&b));
        assert!(store.create(job("default", "a")).is_err());
        assert!(store.create(job("other", "a")).is_ok());
        let (items, _) = store.list::<Job>(Some("default"), |_| true);
        assert_eq!(items.len(), 2);
        assert!(store.remove::<Job>(&key).is_some());
        assert!(store.get::<Job>(&key).is_none());
    }

    #[test]
    fn subscribe_replays_events_after_the_given_version() {
        let store = Store::new();
        store.create(job("default", "a")).unwrap();
        let since = store.resource_version();
        store.create(job("default", "b")).unwrap();
        let past = store.subscribe(since).unwrap().past;
        assert_eq!(past.len(), 1);
        assert_eq!(past[0].type_, EventType::Added);
        assert_eq!(past[0].object.meta().name.as_deref(), Some("b"));
    }
}
