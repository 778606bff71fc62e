// The console's shell: sign-in by API key (sessionStorage only), hash routing
// (#/environments, #/environments/{id}), the environments list.

import "./style.css";
import { ApiError, getJson, onUnauthorised, storeKey, storedKey, type Environment, type KeyInfo } from "./api";
import { empty, errorBanner, fmtTime, h, loading } from "./dom";
import { EnvironmentPage } from "./envpage";

declare global {
  interface Window {
    __twindelta: { cloudReadyMs: number | null; cloudPoints: number | null; cloudTotalPoints: number | null; cloudSource: string | null; modelsDrawn: number };
  }
}
window.__twindelta = { cloudReadyMs: null, cloudPoints: null, cloudTotalPoints: null, cloudSource: null, modelsDrawn: 0 };

const root = document.getElementById("app")!;
let current: { dispose(): void } | null = null;
let me: KeyInfo | null = null;
let signinNotice: HTMLElement | null = null;

onUnauthorised((e) => {
  storeKey(null);
  me = null;
  signinNotice = errorBanner("Unauthorised", `${e.detail.replace(/\.?$/, ".")} Sign in again with a valid key.`, e.code);
  location.hash = "#/signin";
  route();
});

function header(): HTMLElement {
  return h(
    "header",
    { class: "topbar" },
    h("a", { href: "#/environments", class: "brand" }, "twindelta", h("span", {}, " console")),
    me
      ? h(
          "div",
          { class: "who" },
          h("span", { class: "key-name", title: `key ${me.id}` }, me.name),
          h("span", { class: "scopes" }, me.scopes.join(", ")),
          h("button", { class: "link", onclick: () => signOut() }, "Sign out"),
        )
      : null,
  );
}

function signOut(): void {
  storeKey(null);
  me = null;
  location.hash = "#/signin";
}

function mount(...nodes: HTMLElement[]): void {
  current?.dispose();
  current = null;
  root.replaceChildren(header(), ...nodes);
}

function signinPage(): void {
  const input = h("input", {
    type: "password",
    id: "signin-key",
    testid: "signin-key",
    autocomplete: "off",
    placeholder: "td_…",
    "aria-label": "API key",
    required: true,
  });
  const status = h("div", { class: "signin-status" });
  if (signinNotice) status.append(signinNotice);
  const form = h(
    "form",
    { class: "signin card" },
    h("h1", {}, "Sign in"),
    h("p", { class: "muted" }, "Paste an API key. It is kept for this browser tab only (sessionStorage) and sent as a Bearer token to this service."),
    h("label", { for: "signin-key" }, "API key"),
    input,
    h("button", { type: "submit", class: "primary", testid: "signin-submit" }, "Sign in"),
    status,
  );
  form.addEventListener("submit", async (e) => {
    e.preventDefault();
    const key = input.value.trim();
    if (!key) return;
    status.replaceChildren(loading("your key"));
    try {
      me = await getJson<KeyInfo>("/v1/keys/current", key);
      storeKey(key);
      signinNotice = null;
      location.hash = "#/environments";
    } catch (err) {
      const e2 = err as ApiError;
      status.replaceChildren(
        e2.status === 401
          ? errorBanner("Unauthorised", "This key is not valid (unknown or revoked).", e2.code)
          : errorBanner("Sign-in failed", e2.detail ?? String(err), e2.code),
      );
    }
  });
  mount(h("main", { class: "centre" }, form));
  input.focus();
}

async function environmentsPage(): Promise<void> {
  const body = h("section", { class: "card" }, h("h1", {}, "Environments"), loading("environments"));
  mount(h("main", { class: "page" }, body));
  try {
    const envs = await getJson<Environment[]>("/v1/environments");
    body.lastChild?.remove();
    if (envs.length === 0) {
      body.append(empty("No environments yet. An admin key creates one with POST /v1/environments (see the README)."));
      return;
    }
    const table = h(
      "table",
      { class: "table", testid: "env-list" },
      h("thead", {}, h("tr", {}, h("th", {}, "Environment"), h("th", { class: "num" }, "Twin objects"), h("th", {}, "Last snapshot"), h("th", {}, "Twin"), h("th", {}, "Created"))),
    );
    const tbody = h("tbody");
    for (const env of envs) {
      const last = env.last_snapshot;
      const row = h(
        "tr",
        { testid: "env-row", class: "clickable", tabindex: 0, "data-id": env.id },
        h("td", {}, h("a", { href: `#/environments/${env.id}` }, env.name)),
        h("td", { class: "num" }, env.twin_object_count ?? "—"),
        h("td", {}, last ? h("span", {}, `#${last.seq} `, h("span", { class: `badge ${last.state}` }, last.state), ` ${fmtTime(last.created_at)}`) : h("span", { class: "muted" }, "none")),
        h("td", {}, h("span", { class: `badge ${env.twin.status}` }, env.twin.status)),
        h("td", {}, fmtTime(env.created_at)),
      );
      const open = () => (location.hash = `#/environments/${env.id}`);
      row.addEventListener("click", (e) => {
        if (!(e.target as HTMLElement).closest("a")) open();
      });
      row.addEventListener("keydown", (e) => e.key === "Enter" && open());
      tbody.append(row);
    }
    table.append(tbody);
    body.append(h("div", { class: "scroll" }, table));
  } catch (err) {
    body.lastChild?.remove();
    const e = err as ApiError;
    body.append(errorBanner("Could not load the environments", e.detail ?? String(err), e.code));
  }
}

async function ensureSignedIn(): Promise<boolean> {
  const key = storedKey();
  if (!key) return false;
  if (me) return true;
  try {
    me = await getJson<KeyInfo>("/v1/keys/current", key);
    return true;
  } catch {
    return false;
  }
}

async function route(): Promise<void> {
  const hash = location.hash || "#/environments";
  if (hash === "#/signin") return signinPage();
  if (!(await ensureSignedIn())) {
    if (location.hash !== "#/signin") location.hash = "#/signin";
    else signinPage();
    return;
  }
  const envMatch = hash.match(/^#\/environments\/([^/?]+)/);
  if (envMatch) {
    const main = h("main", { class: "env-page" });
    mount(main);
    current = new EnvironmentPage(main, decodeURIComponent(envMatch[1]), me!);
    return;
  }
  return environmentsPage();
}

window.addEventListener("hashchange", () => void route());
void route();
