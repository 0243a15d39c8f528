//! The outbound policy: which hosts the product may connect to, for every network request it
//! makes (a map's URL, a catalog's places, a server's redirects, S3 credential providers).
//! The one home of that rule; `session::catalog` asks here for its places, and every store
//! is built here ([`build_store`]) on a `reqwest` client whose redirect policy and DNS
//! resolver apply it ([`PolicyConnector`]).
//!
//! The rules (the guide's "Remote maps" page says the same):
//!
//! 1. Only `http`, `https` and `s3` URLs are read.
//! 2. Link-local addresses (169.254.0.0/16, where cloud metadata services answer, and
//!    fe80::/10), AWS's IPv6 metadata address (fd00:ec2::254), multicast and broadcast are never
//!    connected to: neither a URL's literal address nor one a host name resolves to. The one
//!    exception is the credential service rule 5 lets the user's configuration ask for (the
//!    instance metadata service, container credentials), which object_store reaches there.
//! 3. Loopback and private addresses (127.0.0.0/8, 10.0.0.0/8, 172.16.0.0/12, 192.168.0.0/16,
//!    100.64.0.0/10, 0.0.0.0, ::1, fc00::/7) are reached only by a URL the user named (or a
//!    host the user's configuration names: an S3 endpoint), or by a redirect from a URL that was
//!    on one. A catalog file on disk is untrusted: its places may name only public hosts,
//!    unless the user sets `SFPMAP_ALLOW_PRIVATE_PLACES=1`. A catalog read from a URL names
//!    only maps on its own server (scheme, host and port), which it was allowed to reach.
//! 4. A redirect is followed only to the same scheme, host and port, unless the user opts in
//!    (`--allow-redirects`, `SFPMAP_ALLOW_REDIRECTS=1`); then never from https to http, and
//!    rules 2 and 3 still hold for its target.
//! 5. No credential provider asks a metadata service unless the user's configuration says
//!    so: `s3://` needs `AWS_ACCESS_KEY_ID` and `AWS_SECRET_ACCESS_KEY`,
//!    `AWS_SKIP_SIGNATURE=true` (a public bucket; any of object_store's true values), a web
//!    identity, container credentials (a relative URI, or a full URI with its token file), or
//!    `SFPMAP_AWS_INSTANCE_METADATA=1` (the EC2 instance's role, from its metadata service);
//!    otherwise it is refused before any request. The provider counted is the one
//!    object_store will use, in its order: a variable it passes over does not count.
//!
//! Behind an HTTP proxy (`HTTP_PROXY`), the proxy resolves host names: rules 1, 2 and 3 hold
//! for literal addresses and redirects, the proxy decides what a name reaches. The proxy's own
//! host name is resolved through rules 2 and 3 like any other (the resolver cannot tell the
//! proxy's connection from a request's): a proxy on a private address is named by that
//! address (`HTTP_PROXY=http://10.0.0.5:3128`), which is connected to without a lookup.

use super::RemoteOptions;
use object_store::client::{HttpClient, HttpConnector};
use object_store::path::Path as StorePath;
use object_store::{ClientConfigKey, ClientOptions, ObjectStore};
use std::net::{IpAddr, Ipv4Addr, Ipv6Addr, SocketAddr, ToSocketAddrs};
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::Arc;
use std::time::Duration;
use url::{Host, Url};

/// The variable that follows redirects to another scheme, host or port.
pub(crate) const ALLOW_REDIRECTS_ENV: &str = "SFPMAP_ALLOW_REDIRECTS";
/// The variable that lets a catalog file on disk name loopback and private hosts.
pub(crate) const ALLOW_PRIVATE_PLACES_ENV: &str = "SFPMAP_ALLOW_PRIVATE_PLACES";
/// The variable that lets S3 take the EC2 instance's role from its metadata service.
pub(crate) const INSTANCE_METADATA_ENV: &str = "SFPMAP_AWS_INSTANCE_METADATA";

/// The most redirects one request follows.
const MAX_REDIRECTS: usize = 10;
/// How long a connection may take to open, and a request in all.
const CONNECT_TIMEOUT: Duration = Duration::from_secs(5);
const REQUEST_TIMEOUT: Duration = Duration::from_secs(120);
/// Whole-object transfers (`objects.rs`: a database of tens of GB) have no total deadline,
/// only this long without a byte, and retry for longer than range reads.
const TRANSFER_READ_TIMEOUT: Duration = Duration::from_secs(60);
const TRANSFER_RETRIES: usize = 10;
const TRANSFER_RETRY_TIMEOUT: Duration = Duration::from_secs(300);

/// What a store is for: its deadlines and retries.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub(crate) enum Traffic {
    /// Range reads of a map: each request small, an unreachable server reported in seconds.
    Ranges,
    /// Whole objects of any size (`objects.rs`): no total deadline, a read timeout, patient
    /// retries.
    WholeObjects,
}

/// Who named a URL: decides whether it may reach loopback and private addresses (rule 3).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub(crate) enum NamedBy {
    /// The user: a command line, an API call.
    User,
    /// A catalog read from a URL: its places are on the catalog's own server.
    #[cfg_attr(not(feature = "localize"), allow(dead_code))]
    RemoteCatalog,
    /// A catalog file on disk.
    #[cfg_attr(not(feature = "localize"), allow(dead_code))]
    LocalCatalog,
}

impl NamedBy {
    fn may_reach_internal(self, options: &RemoteOptions) -> bool {
        match self {
            NamedBy::User | NamedBy::RemoteCatalog => true,
            NamedBy::LocalCatalog => options.allow_private_places,
        }
    }
}

/// What an address is to the policy.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub(crate) enum Class {
    /// Reached by anyone's URL.
    Public,
    /// Loopback or private: reached only from the user's own URL (the words say which).
    Internal(&'static str),
    /// Never connected to (the words say why).
    Never(&'static str),
}

/// The class of `ip`. An IPv6 address that carries an IPv4 one is classed as the IPv4
/// address it reaches: IPv4-mapped (`::ffff:a.b.c.d`), IPv4-compatible (`::a.b.c.d`), 6to4
/// (`2002:AABB:CCDD::/48`, the IPv4 address in bits 16 to 48), NAT64's well-known prefix
/// (`64:ff9b::/96`) and Teredo (`2001::/32`, the client's address inverted in the last 32
/// bits). NAT64's local-use prefix (`64:ff9b:1::/48`) is a translator of the site's own:
/// internal at least, and the most restrictive class of the IPv4 addresses it may embed
/// (RFC 6052's positions for its /48 to /96 prefixes). Site-local `fec0::/10` is internal.
pub(crate) fn classify(ip: IpAddr) -> Class {
    match ip {
        IpAddr::V4(v4) => classify_v4(v4),
        IpAddr::V6(v6) => {
            if let Some(v4) = embedded_v4(v6) {
                return classify_v4(v4);
            }
            let s = v6.segments();
            let b = v6.octets();
            if s[..3] == [0x64, 0xff9b, 1] {
                // RFC 6052's IPv4 positions for a /48, /56, /64 and /96 prefix (bits 64 to 71
                // are the reserved u octet).
                let candidates = [
                    [b[6], b[7], b[9], b[10]],
                    [b[7], b[9], b[10], b[11]],
                    [b[9], b[10], b[11], b[12]],
                    [b[12], b[13], b[14], b[15]],
                ];
                return candidates
                    .into_iter()
                    .map(|o| classify_v4(Ipv4Addr::from(o)))
                    .fold(
                        Class::Internal("NAT64 local-use (64:ff9b:1::/48)"),
                        stricter,
                    );
            }
            if v6 == Ipv6Addr::new(0xfd00, 0xec2, 0, 0, 0, 0, 0, 0x254) {
                Class::Never("AWS's IPv6 instance metadata service")
            } else if s[0] & 0xffc0 == 0xfe80 {
                Class::Never("link-local (fe80::/10)")
            } else if v6.is_multicast() {
                Class::Never("multicast")
            } else if v6.is_loopback() {
                Class::Internal("loopback")
            } else if v6.is_unspecified() {
                Class::Internal("unspecified (this host)")
            } else if s[0] & 0xfe00 == 0xfc00 {
                Class::Internal("unique local (fc00::/7)")
            } else if s[0] & 0xffc0 == 0xfec0 {
                Class::Internal("site-local (fec0::/10)")
            } else {
                Class::Public
            }
        }
    }
}

/// The IPv4 address an IPv6 one reaches, for the forms with one place for it: mapped,
/// compatible (not `::` and `::1`, which are IPv6's own), 6to4, NAT64's well-known prefix and
/// Teredo.
fn embedded_v4(v6: Ipv6Addr) -> Option<Ipv4Addr> {
    let s = v6.segments();
    let join = |hi: u16, lo: u16| Ipv4Addr::from((u32::from(hi) << 16) | u32::from(lo));
    if let Some(v4) = v6.to_ipv4_mapped() {
        Some(v4)
    } else if s[..6] == [0; 6] && !v6.is_unspecified() && !v6.is_loopback() {
        Some(join(s[6], s[7]))
    } else if s[0] == 0x2002 {
        Some(join(s[1], s[2]))
    } else if s[..6] == [0x64, 0xff9b, 0, 0, 0, 0] {
        Some(join(s[6], s[7]))
    } else if s[..2] == [0x2001, 0] {
        Some(join(!s[6], !s[7]))
    } else {
        None
    }
}

/// The more restrictive of two classes (never, then internal, then public).
fn stricter(a: Class, b: Class) -> Class {
    match (a, b) {
        (Class::Never(w), _) | (_, Class::Never(w)) => Class::Never(w),
        (Class::Internal(w), _) | (_, Class::Internal(w)) => Class::Internal(w),
        _ => Class::Public,
    }
}

fn classify_v4(ip: Ipv4Addr) -> Class {
    let o = ip.octets();
    if ip.is_link_local() {
        Class::Never("link-local (169.254.0.0/16, where cloud metadata services answer)")
    } else if ip.is_broadcast() {
        Class::Never("broadcast")
    } else if ip.is_multicast() {
        Class::Never("multicast")
    } else if ip.is_loopback() {
        Class::Internal("loopback")
    } else if o[0] == 0 {
        Class::Internal("unspecified (this host)")
    } else if ip.is_private() {
        Class::Internal("private")
    } else if o[0] == 100 && o[1] & 0xc0 == 64 {
        Class::Internal("shared (100.64.0.0/10)")
    } else {
        Class::Public
    }
}

/// The host of `url` as an address, when it is one.
fn literal(url: &Url) -> Option<IpAddr> {
    match url.host()? {
        Host::Ipv4(ip) => Some(IpAddr::V4(ip)),
        Host::Ipv6(ip) => Some(IpAddr::V6(ip)),
        Host::Domain(_) => None,
    }
}

/// Why a URL `named` may not be read, before anything is sent (rules 1 to 3 for its literal
/// address; a host name is checked when it is resolved).
pub(crate) fn admit(url: &Url, named: NamedBy, options: &RemoteOptions) -> Result<(), String> {
    match url.scheme() {
        "http" | "https" => {}
        "s3" => {
            let builder = object_store::aws::AmazonS3Builder::from_env().with_url(url.as_str());
            return s3_credentials(&builder, options);
        }
        other => {
            return Err(format!(
                "scheme {other}: only http, https and s3 URLs are read"
            ))
        }
    }
    if url.host().is_none() {
        return Err("no host".into());
    }
    match literal(url).map(classify) {
        Some(Class::Never(what)) => Err(never(url.host_str().unwrap_or(""), what)),
        Some(Class::Internal(what)) if !named.may_reach_internal(options) => {
            Err(internal_from_catalog(url.host_str().unwrap_or(""), what))
        }
        _ => Ok(()),
    }
}

/// What every refusal's message starts with.
pub(crate) const REFUSED: &str = "refused by the outbound policy";

/// A rule's words as the refusal's message.
pub(crate) fn refused(rule: String) -> String {
    format!("{REFUSED}: {rule}")
}

fn never(address: &str, what: &str) -> String {
    format!("{address} is {what}: never connected to")
}

fn internal_from_catalog(address: &str, what: &str) -> String {
    format!(
        "{address} is a {what} address, and a catalog file on disk may name only public hosts \
         ({ALLOW_PRIVATE_PLACES_ENV}=1 allows loopback and private ones)"
    )
}

/// The URL of a place whose map the catalog at URL `catalog` names `location`: resolved
/// against the catalog's URL; it must keep the catalog's scheme, host and port (an S3
/// catalog: its bucket), so a downloaded catalog opens neither a local file (`file://`, a
/// path), nor another host, nor plain HTTP for an HTTPS catalog.
#[cfg(feature = "localize")]
pub(crate) fn place_of_remote_catalog(catalog: &str, location: &str) -> Result<String, String> {
    let base = Url::parse(catalog).map_err(|e| format!("the catalog's URL: {e}"))?;
    let joined = base.join(location).map_err(|e| format!("not a URL: {e}"))?;
    let origin = |u: &Url| {
        (
            u.scheme().to_string(),
            u.host_str().map(str::to_string),
            u.port_or_known_default(),
        )
    };
    if origin(&joined) != origin(&base) || !crate::input::is_url(joined.as_str()) {
        return Err(format!(
            "{joined}: a catalog read from a URL names only maps on its own server ({}://{}), \
             never a local file or another host",
            base.scheme(),
            base.host_str().unwrap_or("")
        ));
    }
    Ok(joined.into())
}

/// Whether a local catalog's place `location` is a URL of a scheme that is not read
/// (`file://`, `ftp://`): such a place is refused rather than taken for a relative path.
#[cfg(feature = "localize")]
pub(crate) fn foreign_scheme(location: &str) -> Option<String> {
    let (scheme, _) = location.split_once("://")?;
    let is_scheme = !scheme.is_empty()
        && scheme.starts_with(|c: char| c.is_ascii_alphabetic())
        && scheme
            .chars()
            .all(|c| c.is_ascii_alphanumeric() || "+-.".contains(c));
    (is_scheme && !crate::input::is_url(location)).then(|| {
        format!(
            "scheme {}: only http, https and s3 URLs are read (a local file is named by its path)",
            scheme.to_ascii_lowercase()
        )
    })
}

/// The credential provider object_store 0.14's `AmazonS3Builder::build` takes for a builder
/// configured from the environment, in its order (`aws/builder.rs`): static keys, a web
/// identity, ECS task credentials, EKS Pod Identity (a full URI only with a token file), else
/// the EC2 instance metadata service.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
enum S3Provider {
    /// `AWS_ACCESS_KEY_ID` / `AWS_SECRET_ACCESS_KEY` (either set: the build fails without
    /// the other, before any request).
    Static,
    /// `AWS_WEB_IDENTITY_TOKEN_FILE` and `AWS_ROLE_ARN`: STS.
    WebIdentity,
    /// `AWS_CONTAINER_CREDENTIALS_RELATIVE_URI`: the ECS task metadata service.
    Task,
    /// `AWS_CONTAINER_CREDENTIALS_FULL_URI` and `AWS_CONTAINER_AUTHORIZATION_TOKEN_FILE`.
    EksPod,
    /// None of those: the instance metadata service (`AWS_METADATA_ENDPOINT`, else
    /// 169.254.169.254).
    Instance,
}

/// Which provider object_store builds for `builder`: a variable set to an empty value is
/// set to it, as to object_store.
fn s3_provider(builder: &object_store::aws::AmazonS3Builder) -> S3Provider {
    use object_store::aws::AmazonS3ConfigKey as Key;
    let some = |key: Key| builder.get_config_value(&key).is_some();
    if some(Key::AccessKeyId) || some(Key::SecretAccessKey) {
        S3Provider::Static
    } else if some(Key::WebIdentityTokenFile) && some(Key::RoleArn) {
        S3Provider::WebIdentity
    } else if some(Key::ContainerCredentialsRelativeUri) {
        S3Provider::Task
    } else if some(Key::ContainerCredentialsFullUri) && some(Key::ContainerAuthorizationTokenFile) {
        S3Provider::EksPod
    } else {
        S3Provider::Instance
    }
}

/// A boolean setting as object_store parses it (`config.rs`, `impl Parse for bool`): `true`,
/// `1`, `on`, `yes`, `y` in any case.
fn object_store_true(value: &str) -> bool {
    matches!(
        value.to_ascii_lowercase().as_str(),
        "1" | "true" | "on" | "yes" | "y"
    )
}

/// Rule 5: why an S3 store configured as `builder` may not be built (no credentials the
/// user's configuration asks for), before any request. Accepted only where the provider
/// object_store will use ([`s3_provider`]) is one the configuration names: a variable that
/// object_store would pass over (a full URI without its token file) does not count.
pub(crate) fn s3_credentials(
    builder: &object_store::aws::AmazonS3Builder,
    options: &RemoteOptions,
) -> Result<(), String> {
    use object_store::aws::AmazonS3ConfigKey as Key;
    let set = |key: Key| {
        builder
            .get_config_value(&key)
            .is_some_and(|v| !v.is_empty())
    };
    // Unsigned requests never ask the provider for credentials, whichever it is.
    let unsigned = builder
        .get_config_value(&Key::SkipSignature)
        .is_some_and(|v| object_store_true(&v));
    let configured = unsigned
        || match s3_provider(builder) {
            S3Provider::Static => true,
            S3Provider::WebIdentity => set(Key::WebIdentityTokenFile) && set(Key::RoleArn),
            S3Provider::Task => set(Key::ContainerCredentialsRelativeUri),
            S3Provider::EksPod => {
                set(Key::ContainerCredentialsFullUri) && set(Key::ContainerAuthorizationTokenFile)
            }
            S3Provider::Instance => set(Key::MetadataEndpoint) || options.instance_metadata,
        };
    if configured {
        return Ok(());
    }
    Err(format!(
        "no S3 credentials configured, and sfpmap asks no metadata service for them unless told \
         to: set AWS_ACCESS_KEY_ID and AWS_SECRET_ACCESS_KEY, AWS_SKIP_SIGNATURE=true for a \
         public bucket, AWS_CONTAINER_CREDENTIALS_FULL_URI together with \
         AWS_CONTAINER_AUTHORIZATION_TOKEN_FILE, or {INSTANCE_METADATA_ENV}=1 for the EC2 \
         instance's role"
    ))
}

/// The EKS Pod Identity token file (`AWS_CONTAINER_AUTHORIZATION_TOKEN_FILE`), when
/// object_store will send it: its contents go into a request header as they are, and a
/// control character there (a trailing newline, as `echo` writes) makes object_store panic
/// building the request. Checked when the store is built, naming the file.
fn s3_token_file(builder: &object_store::aws::AmazonS3Builder) -> Result<(), String> {
    use object_store::aws::AmazonS3ConfigKey as Key;
    let unsigned = builder
        .get_config_value(&Key::SkipSignature)
        .is_some_and(|v| object_store_true(&v));
    if unsigned || s3_provider(builder) != S3Provider::EksPod {
        return Ok(());
    }
    let Some(file) = builder.get_config_value(&Key::ContainerAuthorizationTokenFile) else {
        return Ok(());
    };
    let shown = crate::escape::escape_control_characters(&file);
    let token = std::fs::read_to_string(&file)
        .map_err(|e| format!("AWS_CONTAINER_AUTHORIZATION_TOKEN_FILE {shown}: {e}"))?;
    if token.is_empty() || token.chars().any(char::is_control) {
        return Err(format!(
            "AWS_CONTAINER_AUTHORIZATION_TOKEN_FILE {shown}: the token is empty or holds a \
             control character (a trailing newline?), which no request header may: write the \
             token alone, without a line end"
        ));
    }
    Ok(())
}

/// The hosts of the URLs in the user's S3 configuration (endpoints, credential services):
/// theirs may be loopback or private.
fn s3_configured_hosts(builder: &object_store::aws::AmazonS3Builder) -> Vec<String> {
    use object_store::aws::AmazonS3ConfigKey as Key;
    [
        Key::Endpoint,
        Key::S3Endpoint,
        Key::StsEndpoint,
        Key::MetadataEndpoint,
        Key::ContainerCredentialsFullUri,
    ]
    .into_iter()
    .filter_map(|key| builder.get_config_value(&key))
    .filter_map(|v| Url::parse(&v).ok()?.host_str().map(str::to_string))
    .collect()
}

/// The store and object path for `url` (named by `named`), on a client that applies the
/// policy: an HTTP(S) server, or an S3 bucket configured from `AWS_*` variables. Refused
/// (with the rule) before any request when the policy says no.
pub(crate) fn build_store(
    url: &Url,
    named: NamedBy,
    options: &RemoteOptions,
    traffic: Traffic,
) -> Result<(Box<dyn ObjectStore>, StorePath), String> {
    use object_store::{BackoffConfig, RetryConfig};
    admit(url, named, options).map_err(refused)?;
    let describe = |e: object_store::Error| super::describe(&e);
    // Plain http is what the user asked for when the URL (or the S3 endpoint) says so.
    let client = ClientOptions::new()
        .with_allow_http(true)
        .with_connect_timeout(CONNECT_TIMEOUT);
    let (client, retry) = match traffic {
        // Bounded time: an unreachable or failing server is reported within seconds, not
        // after the crate's default of ten retries over three minutes.
        Traffic::Ranges => (
            client.with_timeout(REQUEST_TIMEOUT),
            RetryConfig {
                backoff: BackoffConfig::default(),
                max_retries: 2,
                retry_timeout: Duration::from_secs(15),
            },
        ),
        // A body of many GB takes minutes: a stall is the failure, not the length.
        Traffic::WholeObjects => (
            client
                .with_timeout_disabled()
                .with_read_timeout(TRANSFER_READ_TIMEOUT),
            RetryConfig {
                backoff: BackoffConfig::default(),
                max_retries: TRANSFER_RETRIES,
                retry_timeout: TRANSFER_RETRY_TIMEOUT,
            },
        ),
    };
    let path = StorePath::from_url_path(url.path()).map_err(|e| describe(e.into()))?;
    match url.scheme() {
        "s3" => {
            // `admit` checked its credentials (rule 5) in the same environment.
            let builder = object_store::aws::AmazonS3Builder::from_env().with_url(url.as_str());
            s3_token_file(&builder)?;
            let connector = PolicyConnector::new(s3_configured_hosts(&builder), false, options);
            // Every PUT carries its SHA-256, which the server checks before storing
            // (`objects::upload`); reads are unaffected.
            let store = builder
                .with_checksum_algorithm(object_store::aws::Checksum::SHA256)
                .with_client_options(client)
                .with_retry(retry)
                .with_http_connector(connector)
                .build()
                .map_err(describe)?;
            Ok((Box::new(store), path))
        }
        _ => {
            let host = url.host_str().unwrap_or_default().to_string();
            let internal_ok = named.may_reach_internal(options);
            let origin_internal =
                internal_ok && matches!(literal(url).map(classify), Some(Class::Internal(_)));
            let trusted = if internal_ok { vec![host] } else { Vec::new() };
            let connector = PolicyConnector::new(trusted, origin_internal, options);
            let base = &url[..url::Position::BeforePath];
            let store = object_store::http::HttpBuilder::new()
                .with_url(base)
                .with_client_options(client)
                .with_retry(retry)
                .with_http_connector(connector)
                .build()
                .map_err(describe)?;
            Ok((Box::new(store), path))
        }
    }
}

/// What a store's clients share: which names may resolve to internal addresses, whether
/// the URL named was on one, and whether redirects may leave its origin.
#[derive(Debug)]
struct State {
    /// Host names whose loopback and private addresses are accepted (the user's URL's, the
    /// user's S3 endpoints).
    trusted_hosts: Vec<String>,
    /// The URL named was on a loopback or private address: redirects may go to one.
    origin_internal: AtomicBool,
    allow_redirects: bool,
}

/// A refusal by the policy, as the error a client's request fails with.
#[derive(Debug)]
struct Refused(String);

impl std::fmt::Display for Refused {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(&refused(self.0.clone()))
    }
}

impl std::error::Error for Refused {}

impl State {
    /// Rules 2 and 3 for the addresses `host` resolved to.
    fn check_resolved(&self, host: &str, addrs: &[IpAddr]) -> Result<(), String> {
        let trusted = self
            .trusted_hosts
            .iter()
            .any(|t| t.eq_ignore_ascii_case(host));
        for &ip in addrs {
            match classify(ip) {
                Class::Never(what) => return Err(never(&format!("{host} ({ip})"), what)),
                Class::Internal(_) if trusted => {
                    self.origin_internal.store(true, Ordering::Relaxed)
                }
                Class::Internal(_) if self.origin_internal.load(Ordering::Relaxed) => {}
                Class::Internal(what) => {
                    return Err(format!(
                        "{host} resolves to {ip}, a {what} address, which only a URL you named \
                         (or one it redirects to, when it is on such an address itself) may reach"
                    ))
                }
                Class::Public => {}
            }
        }
        Ok(())
    }

    /// Rule 4, and rules 1 to 3 for a literal address, for a redirect from the request's
    /// first URL `origin` to `target`.
    fn check_redirect(&self, origin: &Url, target: &Url) -> Result<(), String> {
        if !matches!(target.scheme(), "http" | "https") {
            return Err(format!(
                "scheme {}: only http and https are followed",
                target.scheme()
            ));
        }
        let same = origin.scheme() == target.scheme()
            && origin.host_str() == target.host_str()
            && origin.port_or_known_default() == target.port_or_known_default();
        if same {
            return Ok(());
        }
        if !self.allow_redirects {
            return Err(format!(
                "another scheme, host or port than {}://{} (--allow-redirects or \
                 {ALLOW_REDIRECTS_ENV}=1 follows it)",
                origin.scheme(),
                &origin[url::Position::BeforeHost..url::Position::AfterPort]
            ));
        }
        downgrade(origin, target)?;
        match literal(target).map(classify) {
            Some(Class::Never(what)) => Err(never(target.host_str().unwrap_or(""), what)),
            Some(Class::Internal(what)) if !self.origin_internal.load(Ordering::Relaxed) => {
                Err(format!(
                    "{} is a {what} address, and the URL named was not on one",
                    target.host_str().unwrap_or("")
                ))
            }
            _ => Ok(()),
        }
    }

    fn redirect(&self, attempt: reqwest::redirect::Attempt<'_>) -> reqwest::redirect::Action {
        let previous = attempt.previous();
        if previous.len() > MAX_REDIRECTS {
            let error = Refused(format!("more than {MAX_REDIRECTS} redirects"));
            return attempt.error(error);
        }
        let checked = match (previous.first(), previous.last()) {
            (Some(origin), Some(last)) => {
                // Never down to http from any https hop of the chain, not only the first.
                downgrade(last, attempt.url())
                    .and_then(|()| self.check_redirect(origin, attempt.url()))
            }
            _ => Ok(()),
        };
        match checked {
            Ok(()) => attempt.follow(),
            Err(rule) => {
                let error = Refused(format!("redirect to {}: {rule}", attempt.url()));
                attempt.error(error)
            }
        }
    }
}

/// Refuses a redirect from an https URL to a plain http one.
fn downgrade(from: &Url, to: &Url) -> Result<(), String> {
    if from.scheme() == "https" && to.scheme() == "http" {
        Err(format!("from https ({from}) to plain http"))
    } else {
        Ok(())
    }
}

/// Resolves host names as the system does, then applies rules 2 and 3 to every address.
struct Resolver(Arc<State>);

impl reqwest::dns::Resolve for Resolver {
    fn resolve(&self, name: reqwest::dns::Name) -> reqwest::dns::Resolving {
        let state = Arc::clone(&self.0);
        let host = name.as_str().to_string();
        Box::pin(async move {
            let lookup = host.clone();
            let addrs: Vec<SocketAddr> = tokio::task::spawn_blocking(move || {
                (lookup.as_str(), 0)
                    .to_socket_addrs()
                    .map(Iterator::collect)
            })
            .await??;
            let ips: Vec<IpAddr> = addrs.iter().map(SocketAddr::ip).collect();
            state.check_resolved(&host, &ips).map_err(Refused)?;
            Ok(Box::new(addrs.into_iter()) as reqwest::dns::Addrs)
        })
    }
}

/// object_store's HTTP connector with the policy in its client: redirects checked by
/// [`State::check_redirect`], every resolved address by [`State::check_resolved`]. Built
/// once a store; object_store asks it for each client the store uses (its requests and its
/// credential providers').
#[derive(Debug)]
pub(crate) struct PolicyConnector {
    state: Arc<State>,
}

impl PolicyConnector {
    fn new(
        trusted_hosts: Vec<String>,
        origin_internal: bool,
        options: &RemoteOptions,
    ) -> PolicyConnector {
        PolicyConnector {
            state: Arc::new(State {
                trusted_hosts,
                origin_internal: AtomicBool::new(origin_internal),
                allow_redirects: options.allow_redirects,
            }),
        }
    }
}

impl PolicyConnector {
    /// The client, `https_only` unless `allow_http`.
    fn client(&self, allow_http: bool) -> reqwest::Result<reqwest::Client> {
        self.builder(allow_http).build()
    }

    /// [`PolicyConnector::client`]'s builder.
    fn builder(&self, allow_http: bool) -> reqwest::ClientBuilder {
        let state = Arc::clone(&self.state);
        reqwest::Client::builder()
            .user_agent(concat!("sfpmap/", env!("CARGO_PKG_VERSION")))
            .connect_timeout(CONNECT_TIMEOUT)
            .timeout(REQUEST_TIMEOUT)
            // Compression would change Content-Length, which object_store reads sizes from.
            .no_gzip()
            .no_brotli()
            .no_zstd()
            .no_deflate()
            .redirect(reqwest::redirect::Policy::custom(move |attempt| {
                state.redirect(attempt)
            }))
            .dns_resolver(Arc::new(Resolver(Arc::clone(&self.state))))
            .https_only(!allow_http)
    }
}

impl HttpConnector for PolicyConnector {
    fn connect(&self, options: &ClientOptions) -> object_store::Result<HttpClient> {
        let allow_http = options
            .get_config_value(&ClientConfigKey::AllowHttp)
            .is_some_and(|v| v == "true");
        let client = self
            .client(allow_http)
            .map_err(|e| object_store::Error::Generic {
                store: "HTTP client",
                source: Box::new(e),
            })?;
        Ok(HttpClient::new(client))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn ip(s: &str) -> IpAddr {
        s.parse().unwrap()
    }

    fn url(s: &str) -> Url {
        Url::parse(s).unwrap()
    }

    fn state(trusted: &[&str], origin_internal: bool, allow_redirects: bool) -> State {
        State {
            trusted_hosts: trusted.iter().map(|s| s.to_string()).collect(),
            origin_internal: AtomicBool::new(origin_internal),
            allow_redirects,
        }
    }

    #[test]
    fn addresses_are_classed_link_local_internal_or_public() {
        for never in [
            "169.254.169.254",
            "169.254.0.1",
            "fe80::1",
            "febf::1",
            "fd00:ec2::254",
            "::ffff:169.254.169.254",
            "64:ff9b::a9fe:a9fe",
            // IPv4-compatible, 6to4, NAT64 local-use and Teredo forms of 169.254.169.254.
            "::169.254.169.254",
            "::a9fe:a9fe",
            "2002:a9fe:a9fe::1",
            "64:ff9b:1::a9fe:a9fe",
            "64:ff9b:1:a9fe:a9:fe00::",
            "2001:0:4136:e378:8000:63bf:5601:5601",
            "255.255.255.255",
            "224.0.0.1",
            "ff02::1",
        ] {
            assert!(matches!(classify(ip(never)), Class::Never(_)), "{never}");
        }
        for internal in [
            "127.0.0.1",
            "127.0.0.2",
            "10.1.2.3",
            "172.16.0.1",
            "172.31.255.255",
            "192.168.1.1",
            "100.64.0.1",
            "0.0.0.0",
            "::1",
            "::",
            "fd12::1",
            "::ffff:127.0.0.1",
            "::127.0.0.1",
            "::10.0.0.1",
            "2002:7f00:1::",
            "2002:c0a8:101::1",
            "64:ff9b::7f00:1",
            "64:ff9b::a00:1",
            "64:ff9b:1::808:808",
            "fec0::1",
            "feff::1",
        ] {
            assert!(
                matches!(classify(ip(internal)), Class::Internal(_)),
                "{internal}"
            );
        }
        for public in [
            "8.8.8.8",
            "172.32.0.1",
            "100.128.0.1",
            "2001:db8::1",
            "1.1.1.1",
            "::8.8.8.8",
            "2002:808:808::1",
            "64:ff9b::808:808",
            "2001:0:4136:e378:8000:63bf:f7f7:f7f7",
        ] {
            assert_eq!(classify(ip(public)), Class::Public, "{public}");
        }
    }

    #[test]
    fn a_url_is_admitted_by_scheme_and_literal_address() {
        let options = RemoteOptions::default();
        let user = NamedBy::User;
        let local = NamedBy::LocalCatalog;
        assert!(admit(&url("http://127.0.0.1:8080/m.sfpm"), user, &options).is_ok());
        assert!(admit(&url("https://maps.example/m.sfpm"), local, &options).is_ok());
        let err = admit(&url("http://169.254.169.254/latest/m"), user, &options).unwrap_err();
        assert!(err.contains("link-local"), "{err}");
        let err = admit(&url("http://[fe80::1]/m"), local, &options).unwrap_err();
        assert!(err.contains("link-local"), "{err}");
        let err = admit(&url("http://10.0.0.1/m"), local, &options).unwrap_err();
        assert!(err.contains(ALLOW_PRIVATE_PLACES_ENV), "{err}");
        let err = admit(&url("file:///etc/passwd"), user, &options).unwrap_err();
        assert!(err.contains("scheme file"), "{err}");
        let allowed = RemoteOptions {
            allow_private_places: true,
            ..RemoteOptions::default()
        };
        assert!(admit(&url("http://10.0.0.1/m"), local, &allowed).is_ok());
        assert!(admit(&url("http://169.254.169.254/m"), local, &allowed).is_err());
    }

    #[test]
    fn redirects_stay_on_their_origin_unless_allowed() {
        let from = url("http://127.0.0.1:8080/m.sfpm");
        let strict = state(&["127.0.0.1"], true, false);
        assert!(strict
            .check_redirect(&from, &url("http://127.0.0.1:8080/other.sfpm"))
            .is_ok());
        for target in [
            "http://127.0.0.2:8080/m.sfpm",
            "http://127.0.0.1:8081/m.sfpm",
            "https://127.0.0.1:8080/m.sfpm",
            "http://maps.example/m.sfpm",
        ] {
            let err = strict.check_redirect(&from, &url(target)).unwrap_err();
            assert!(err.contains(ALLOW_REDIRECTS_ENV), "{target}: {err}");
        }
        let open = state(&["127.0.0.1"], true, true);
        assert!(open
            .check_redirect(&from, &url("http://127.0.0.2:9/m"))
            .is_ok());
        for never in [
            "http://169.254.169.254/latest/meta-data/",
            "http://[fe80::1]/m",
            "http://[::ffff:169.254.169.254]/m",
        ] {
            let err = open.check_redirect(&from, &url(never)).unwrap_err();
            assert!(err.contains("never connected to"), "{never}: {err}");
        }
        let err = open
            .check_redirect(&from, &url("file:///etc/passwd"))
            .unwrap_err();
        assert!(err.contains("scheme file"), "{err}");
        // From a public origin: no internal target, no downgrade to http.
        let public = state(&["maps.example"], false, true);
        let from = url("https://maps.example/m.sfpm");
        assert!(public
            .check_redirect(&from, &url("http://10.0.0.1/m"))
            .is_err());
        assert!(public
            .check_redirect(&from, &url("http://cdn.example/m"))
            .is_err());
        assert!(public
            .check_redirect(&from, &url("https://cdn.example/m"))
            .is_ok());
        // Any https hop of a chain (`redirect` checks the last one too), not only the first.
        let hop = url("https://cdn.example/m");
        assert!(downgrade(&hop, &url("http://cdn.example/m")).is_err());
        assert!(downgrade(&url("http://a.example/m"), &hop).is_ok());
    }

    #[test]
    fn resolved_addresses_follow_the_same_rules() {
        let s = state(&["maps.internal"], false, true);
        // A name the user gave may be internal; then so may the hosts it redirects to.
        assert!(s.check_resolved("cdn.internal", &[ip("10.0.0.9")]).is_err());
        assert!(s.check_resolved("maps.internal", &[ip("10.0.0.8")]).is_ok());
        assert!(s.check_resolved("cdn.internal", &[ip("10.0.0.9")]).is_ok());
        // Never link-local, whoever named it.
        let err = s
            .check_resolved("maps.internal", &[ip("10.0.0.8"), ip("169.254.169.254")])
            .unwrap_err();
        assert!(
            err.contains("169.254.169.254") && err.contains("link-local"),
            "{err}"
        );
        // A catalog file's name resolving to loopback.
        let c = state(&[], false, false);
        let err = c
            .check_resolved("localhost", &[ip("127.0.0.1")])
            .unwrap_err();
        assert!(err.contains("loopback"), "{err}");
        assert!(c
            .check_resolved("maps.example", &[ip("93.184.216.34")])
            .is_ok());
    }

    /// The client asks the policy for every name it resolves: `localhost` from a catalog
    /// file is refused without a connection. (Without a proxy: a proxy resolves names
    /// itself, so the test's clients ignore the environment's proxy variables.)
    #[test]
    fn the_client_resolves_names_through_the_policy() {
        let listener = std::net::TcpListener::bind("127.0.0.1:0").unwrap();
        listener.set_nonblocking(true).unwrap();
        let port = listener.local_addr().unwrap().port();
        let connector = PolicyConnector::new(Vec::new(), false, &RemoteOptions::default());
        let client = connector.builder(true).no_proxy().build().unwrap();
        let runtime = tokio::runtime::Builder::new_current_thread()
            .enable_all()
            .build()
            .unwrap();
        let url = format!("http://localhost:{port}/m.sfpm");
        let err = runtime
            .block_on(async { client.get(&url).send().await })
            .unwrap_err();
        let text = super::super::describe(&err);
        assert!(
            text.contains("loopback") && text.contains("outbound policy"),
            "{text}"
        );
        assert!(listener.accept().is_err(), "connected");
        // The user's own name may be loopback.
        let trusted =
            PolicyConnector::new(vec!["localhost".into()], false, &RemoteOptions::default());
        let client = trusted.builder(true).no_proxy().build().unwrap();
        let _ = runtime.block_on(async {
            let sent = client.get(&url).send();
            tokio::time::timeout(Duration::from_millis(500), sent).await
        });
        assert!(listener.accept().is_ok(), "not connected");
    }

    #[test]
    #[cfg(feature = "localize")]
    fn remote_catalog_places_stay_on_its_server() {
        let c = "http://127.0.0.1:8080/cat/city.sfpc";
        assert_eq!(
            place_of_remote_catalog(c, "s1.sfpm").unwrap(),
            "http://127.0.0.1:8080/cat/s1.sfpm"
        );
        assert_eq!(
            place_of_remote_catalog(c, "/m/s1.sfpm").unwrap(),
            "http://127.0.0.1:8080/m/s1.sfpm"
        );
        for bad in [
            "file:///etc/passwd",
            "http://169.254.169.254/m.sfpm",
            "http://127.0.0.2:8080/m.sfpm",
            "https://127.0.0.1:8080/m.sfpm",
            "s3://bucket/m.sfpm",
        ] {
            let err = place_of_remote_catalog(c, bad).unwrap_err();
            assert!(err.contains("its own server"), "{bad}: {err}");
        }
        assert!(foreign_scheme("file:///etc/passwd").is_some());
        assert!(foreign_scheme("FTP://host/m").is_some());
        assert!(foreign_scheme("s1/map.sfpm").is_none());
        assert!(foreign_scheme("http://host/m").is_none());
    }

    #[test]
    fn s3_needs_credentials_the_user_configured() {
        use object_store::aws::{AmazonS3Builder, AmazonS3ConfigKey as Key};
        let options = RemoteOptions::default();
        let bare = AmazonS3Builder::new().with_url("s3://bucket/m.sfpm");
        let err = s3_credentials(&bare, &options).unwrap_err();
        assert!(err.contains("AWS_ACCESS_KEY_ID") && err.contains(INSTANCE_METADATA_ENV));
        for (key, value) in [
            (Key::AccessKeyId, "id"),
            (Key::SkipSignature, "true"),
            (Key::ContainerCredentialsRelativeUri, "/v2/credentials"),
            (Key::MetadataEndpoint, "http://127.0.0.1:9"),
        ] {
            let b = bare.clone().with_config(key, value);
            assert!(s3_credentials(&b, &options).is_ok(), "{key:?}");
        }
        let b = bare.clone().with_config(Key::SkipSignature, "false");
        assert!(s3_credentials(&b, &options).is_err());
        let instance = RemoteOptions {
            instance_metadata: true,
            ..RemoteOptions::default()
        };
        assert!(s3_credentials(&bare, &instance).is_ok());
    }

    /// Finding 4 and 11 of issue 32's review: a variable counts only where object_store's
    /// builder takes the provider it names, in its order (`AWS_CONTAINER_CREDENTIALS_FULL_URI`
    /// needs `AWS_CONTAINER_AUTHORIZATION_TOKEN_FILE`, or object_store asks the instance
    /// metadata service), and `AWS_SKIP_SIGNATURE` takes object_store's true values.
    #[test]
    fn s3_credentials_count_only_the_provider_object_store_uses() {
        use object_store::aws::{AmazonS3Builder, AmazonS3ConfigKey as Key};
        let options = RemoteOptions::default();
        let bare = AmazonS3Builder::new().with_url("s3://bucket/m.sfpm");
        let with = |pairs: &[(Key, &str)]| {
            pairs
                .iter()
                .fold(bare.clone(), |b, (k, v)| b.with_config(*k, *v))
        };
        let full = (Key::ContainerCredentialsFullUri, "http://127.0.0.1:9/creds");
        let token = (Key::ContainerAuthorizationTokenFile, "/run/token");
        // A full URI alone: object_store falls back to the instance provider.
        let b = with(&[full]);
        assert_eq!(s3_provider(&b), S3Provider::Instance);
        let err = s3_credentials(&b, &options).unwrap_err();
        assert!(
            err.contains("AWS_CONTAINER_AUTHORIZATION_TOKEN_FILE") && err.contains("FULL_URI"),
            "{err}"
        );
        // With its token file: EKS Pod Identity.
        let b = with(&[full, token]);
        assert_eq!(s3_provider(&b), S3Provider::EksPod);
        assert!(s3_credentials(&b, &options).is_ok());
        // The token file alone, an empty full URI, or a role without its token: nothing.
        for pairs in [
            vec![token],
            vec![(Key::ContainerCredentialsFullUri, ""), token],
            vec![(Key::RoleArn, "arn:aws:iam::1:role/r")],
            vec![(Key::WebIdentityTokenFile, "/run/wi")],
            // object_store takes an empty relative URI (169.254.170.2 itself): refused.
            vec![(Key::ContainerCredentialsRelativeUri, "")],
        ] {
            let b = with(&pairs);
            assert!(s3_credentials(&b, &options).is_err(), "{pairs:?}");
        }
        // The order: static keys first, then a web identity, a relative URI, a full URI.
        let b = with(&[(Key::AccessKeyId, "id"), full]);
        assert_eq!(s3_provider(&b), S3Provider::Static);
        let b = with(&[
            (Key::WebIdentityTokenFile, "/run/wi"),
            (Key::RoleArn, "arn:aws:iam::1:role/r"),
            full,
            token,
        ]);
        assert_eq!(s3_provider(&b), S3Provider::WebIdentity);
        assert!(s3_credentials(&b, &options).is_ok());
        let b = with(&[(Key::ContainerCredentialsRelativeUri, "/v2/c"), full]);
        assert_eq!(s3_provider(&b), S3Provider::Task);
        assert!(s3_credentials(&b, &options).is_ok());
        // AWS_SKIP_SIGNATURE: what object_store reads as true, in any case.
        for yes in ["true", "True", "TRUE", "1", "yes", "Y", "on"] {
            let b = with(&[(Key::SkipSignature, yes)]);
            assert!(s3_credentials(&b, &options).is_ok(), "{yes}");
        }
        for no in ["false", "False", "0", "no", "off", "", "maybe"] {
            let b = with(&[(Key::SkipSignature, no)]);
            assert!(s3_credentials(&b, &options).is_err(), "{no}");
        }
    }

    /// The EKS token file goes into a header as it is: one ending in a newline made
    /// object_store panic building the request. Refused when the store is built, naming it.
    #[test]
    fn an_eks_token_file_with_a_control_character_is_refused_naming_it() {
        use object_store::aws::{AmazonS3Builder, AmazonS3ConfigKey as Key};
        let t = tempfile::tempdir().unwrap();
        let file = |name: &str, text: &str| {
            let path = t.path().join(name);
            std::fs::write(&path, text).unwrap();
            path.to_str().unwrap().to_string()
        };
        let builder = |token_file: &str| {
            AmazonS3Builder::new()
                .with_url("s3://bucket/m.sfpm")
                .with_config(Key::ContainerCredentialsFullUri, "http://127.0.0.1:9/c")
                .with_config(Key::ContainerAuthorizationTokenFile, token_file)
        };
        assert!(s3_token_file(&builder(&file("good", "eyJhbGciOi.x.y"))).is_ok());
        for (name, text) in [
            ("newline", "eyJhbGciOi.x.y\n"),
            ("cr", "eyJ\r\nX-Evil: 1"),
            ("empty", ""),
        ] {
            let path = file(name, text);
            let err = s3_token_file(&builder(&path)).unwrap_err();
            assert!(
                err.contains(&path) && err.contains("control character"),
                "{name}: {err}"
            );
        }
        let missing = t.path().join("missing").to_str().unwrap().to_string();
        let err = s3_token_file(&builder(&missing)).unwrap_err();
        assert!(err.contains(&missing), "{err}");
        // Not read where object_store does not send it: static keys, unsigned requests.
        let bad = file("bad", "tok\n");
        let keyed = builder(&bad)
            .with_config(Key::AccessKeyId, "id")
            .with_config(Key::SecretAccessKey, "secret");
        assert!(s3_token_file(&keyed).is_ok());
        let unsigned = builder(&bad).with_config(Key::SkipSignature, "true");
        assert!(s3_token_file(&unsigned).is_ok());
    }
}
