"""Webhook subscriptions and deliveries: rows first, HTTP second.

Modules: :mod:`.signing` (Standard Webhooks signatures), :mod:`.targets` (which addresses
may receive), :mod:`.subscriptions` (and their secrets), :mod:`.fanout` (event to deliveries),
:mod:`.payload` (the CloudEvents body), :mod:`app.core.eventschema` (its published JSON Schema),
:mod:`.adapters` (Azure Digital Twins and Eclipse Ditto bodies, one per changed twin
instance), :mod:`.delivery` (claim, send, record),
:mod:`.transport` (the pinned, deadline-bound connection), :mod:`.dispatch` (beat's
dispatcher), :mod:`.delivery_log` (the log and redelivery). Import from this package.

An event is recorded in the transaction of the state change that causes it
(:func:`app.core.events.record`); :func:`fan_out` adds one pending delivery per matching
active subscription in that same transaction and enqueues ``webhooks.deliver`` after commit.

Ordering. Deliveries of one subscription and one environment share an ``ordering_key`` and
are sent one at a time, oldest first (``seq``, then id): only the *head* (the oldest pending
delivery of its key) may be claimed, so a later event waits while an earlier one is retrying.
Different keys never wait for each other: each delivery is its own task.

Scheduling lives in the database. A failed attempt sets ``next_attempt_at`` from
``Settings.webhook_retry_schedule_s`` (with ±20 % jitter) and releases the delivery; the
``webhooks.dispatch`` beat task sends a deliver message for every head that has come due
(and re-sends one whose message seems lost). No worker thread sleeps, and a worker that dies
mid-schedule loses nothing: the next dispatcher tick finds the row.

Claiming. :func:`claim` takes a lease (``locked_until``) with a conditional UPDATE guarded by
the attempt counter, so two workers never send the same attempt; the counter is also the
fencing token that :func:`record_attempt` checks before it changes the delivery.

A deliver task is: ``claim`` (short transaction) → :func:`send` (no session open) →
``record_attempt`` (short transaction).

Hostile receivers and networks. :func:`send` gives each attempt one overall deadline
(``Settings.webhook_timeout_s``: lookup, connect, TLS, request, response headers and excerpt),
so a receiver that trickles one byte at a time cannot hold a worker thread past it; the lease
is that deadline plus :data:`LEASE_MARGIN_S` and an attempt never runs into the margin, so a
lease never expires under a live attempt. The host is resolved once per attempt, every address
checked again (DNS can change since the subscription was made), and the connection goes to a
checked address: no second lookup that a rebinding DNS server could answer differently, and no
proxy from the environment. TLS verifies the certificate against the URL's host name.

Signatures follow Standard Webhooks: ``webhook-id`` (the event id, the same on every retry),
``webhook-timestamp`` (unix seconds of the attempt) and ``webhook-signature:
v1,<base64 HMAC-SHA256 of "{id}.{timestamp}.{body}">`` keyed with the base64-decoded secret
after its ``whsec_`` prefix. After :func:`rotate_secret` the header carries one signature per
valid secret, ``v1,<new> v1,<previous>``, until the overlap ends. :func:`verify_signature` is
the receiver's side. Secrets are stored encrypted (:mod:`app.core.secretbox`).
"""

from __future__ import annotations

from app.core.eventschema import (
    EVENTS_SCHEMA_ID,
    dataschema,
    event_schema,
)
from app.core.webhooks.adapters import (
    ADT_MODEL_ID,
    CONTENT_TYPES,
    InstanceChange,
    WebhookFormat,
    adt_patch,
    ditto_merge_patch,
    ditto_thing_id,
    instance_changes,
)
from app.core.webhooks.delivery import (
    LEASE_MARGIN_S,
    Claim,
    Outcome,
    attempt_budget_s,
    claim,
    lease_s,
    record_attempt,
    retry_delay_s,
    send,
)
from app.core.webhooks.delivery_log import (
    describe,
    get_delivery,
    list_deliveries,
    redeliver,
)
from app.core.webhooks.dispatch import (
    REDISPATCH_AFTER_S,
    dispatch_due,
)
from app.core.webhooks.fanout import (
    DELIVER_TASK,
    DISPATCH_TASK,
    fan_out,
    ordering_key,
)
from app.core.webhooks.payload import (
    cloudevent,
)
from app.core.webhooks.signing import (
    SECRET_PREFIX,
    WebhookVerificationError,
    new_secret,
    sign,
    signed_headers,
    verify_signature,
)
from app.core.webhooks.subscriptions import (
    create_subscription,
    current_secret,
    deactivate,
    get_subscription,
    list_subscriptions,
    reencrypt_secrets,
    rotate_secret,
    signing_secrets,
)
from app.core.webhooks.targets import (
    IpAddress,
    Network,
    Target,
    allowed_networks,
    check_target,
    resolve_target,
)
from app.core.webhooks.transport import (
    tls_context,
)

__all__ = [
    "ADT_MODEL_ID",
    "CONTENT_TYPES",
    "DELIVER_TASK",
    "DISPATCH_TASK",
    "EVENTS_SCHEMA_ID",
    "LEASE_MARGIN_S",
    "REDISPATCH_AFTER_S",
    "SECRET_PREFIX",
    "Claim",
    "InstanceChange",
    "IpAddress",
    "Network",
    "Outcome",
    "Target",
    "WebhookFormat",
    "WebhookVerificationError",
    "adt_patch",
    "allowed_networks",
    "attempt_budget_s",
    "check_target",
    "claim",
    "cloudevent",
    "create_subscription",
    "current_secret",
    "dataschema",
    "deactivate",
    "describe",
    "dispatch_due",
    "ditto_merge_patch",
    "ditto_thing_id",
    "event_schema",
    "fan_out",
    "get_delivery",
    "get_subscription",
    "instance_changes",
    "lease_s",
    "list_deliveries",
    "list_subscriptions",
    "new_secret",
    "ordering_key",
    "record_attempt",
    "redeliver",
    "reencrypt_secrets",
    "resolve_target",
    "retry_delay_s",
    "rotate_secret",
    "send",
    "sign",
    "signed_headers",
    "signing_secrets",
    "tls_context",
    "verify_signature",
]
