// A small DOM builder and the shared empty / loading / error states.

type Child = Node | string | number | null | undefined | false;
type Attrs = Record<string, string | number | boolean | null | undefined | EventListener>;

export function h<K extends keyof HTMLElementTagNameMap>(tag: K, attrs: Attrs = {}, ...children: Child[]): HTMLElementTagNameMap[K] {
  const el = document.createElement(tag);
  for (const [k, v] of Object.entries(attrs)) {
    if (v === null || v === undefined || v === false) continue;
    if (k.startsWith("on") && typeof v === "function") el.addEventListener(k.slice(2), v as EventListener);
    else if (k === "testid") el.dataset.testid = String(v);
    else if (k === "class") el.className = String(v);
    else if (v === true) el.setAttribute(k, "");
    else el.setAttribute(k, String(v));
  }
  append(el, ...children);
  return el;
}

export function append(el: Element, ...children: Child[]): void {
  for (const c of children) {
    if (c === null || c === undefined || c === false) continue;
    el.append(c instanceof Node ? c : String(c));
  }
}

export function svg<K extends keyof SVGElementTagNameMap>(tag: K, attrs: Record<string, string | number> = {}): SVGElementTagNameMap[K] {
  const el = document.createElementNS("http://www.w3.org/2000/svg", tag);
  for (const [k, v] of Object.entries(attrs)) {
    if (k === "testid") el.setAttribute("data-testid", String(v));
    else el.setAttribute(k, String(v));
  }
  return el;
}

export function loading(what: string): HTMLElement {
  return h("div", { class: "state loading", role: "status" }, h("span", { class: "spinner" }), `Loading ${what}…`);
}

export function empty(text: string): HTMLElement {
  return h("div", { class: "state empty" }, text);
}

export function errorBanner(title: string, detail: string, code?: string): HTMLElement {
  return h(
    "div",
    { class: "error-banner", role: "alert", testid: "error-banner" },
    h("strong", {}, title),
    code ? h("code", {}, code) : null,
    h("div", { class: "detail" }, detail),
  );
}

export function fmtTime(iso: string | null | undefined): string {
  if (!iso) return "—";
  const d = new Date(iso);
  return Number.isNaN(d.getTime()) ? iso : d.toLocaleString(undefined, { dateStyle: "short", timeStyle: "medium" });
}

export function fmtNum(x: unknown, digits = 3): string {
  if (typeof x !== "number" || !Number.isFinite(x)) return x === null || x === undefined ? "—" : String(x);
  return Math.abs(x) >= 1e5 ? x.toLocaleString() : Number(x.toFixed(digits)).toString();
}

export function shortId(id: string | null | undefined): string {
  return id ? id.slice(0, 8) : "—";
}
