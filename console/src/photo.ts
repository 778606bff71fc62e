// The photo view: one capture image (fetched with the key, shown as a blob URL) with the
// detector's boxes and, for a change's view, the cluster's re-projected outline (SVG in
// image pixels, so it scales with the photo).

import { request, type ApiError, type ChangeView, type ImageInfo } from "./api";
import { append, errorBanner, fmtNum, h, loading, svg } from "./dom";

export interface PhotoRequest {
  snapshotId: string;
  image: ImageInfo | null;
  name: string;
  view: ChangeView | null;
  colour: string | null;
  title: string | null;
  siblings: string[];
  onNavigate: (name: string) => void;
}

export class PhotoView {
  private overlay: HTMLElement | null = null;
  private url: string | null = null;
  private keyHandler = (e: KeyboardEvent) => this.onKey(e);
  private current: PhotoRequest | null = null;

  constructor(private readonly host: HTMLElement) {}

  close(): void {
    this.overlay?.remove();
    this.overlay = null;
    if (this.url) URL.revokeObjectURL(this.url);
    this.url = null;
    this.current = null;
    document.removeEventListener("keydown", this.keyHandler);
  }

  private onKey(e: KeyboardEvent): void {
    if (!this.current) return;
    if (e.key === "Escape") return this.close();
    const i = this.current.siblings.indexOf(this.current.name);
    if (e.key === "ArrowRight" && i >= 0 && i + 1 < this.current.siblings.length) this.current.onNavigate(this.current.siblings[i + 1]);
    if (e.key === "ArrowLeft" && i > 0) this.current.onNavigate(this.current.siblings[i - 1]);
  }

  open(req: PhotoRequest): void {
    this.close();
    this.current = req;
    document.addEventListener("keydown", this.keyHandler);
    const stage = h("div", { class: "photo-stage" }, loading(req.name));
    const i = req.siblings.indexOf(req.name);
    const nav = h(
      "div",
      { class: "photo-nav" },
      h("button", { class: "small", disabled: i <= 0, onclick: () => req.onNavigate(req.siblings[i - 1]) }, "← previous"),
      h("span", { class: "muted" }, i >= 0 ? `${i + 1} / ${req.siblings.length}` : ""),
      h("button", { class: "small", disabled: i < 0 || i + 1 >= req.siblings.length, onclick: () => req.onNavigate(req.siblings[i + 1]) }, "next →"),
    );
    const info = h("div", { class: "photo-info" });
    const dets = req.image?.detections ?? [];
    append(
      info,
      h("span", {}, `${dets.length} detection${dets.length === 1 ? "" : "s"}`),
      req.view ? h("span", {}, ` · outline IoU with the detection ${fmtNum(req.view.iou, 2)}${req.view.counted ? "" : " (not counted)"}`) : null,
      req.image && !req.image.registered ? h("span", { class: "warn" }, " · not registered by the reconstruction") : null,
    );
    const dialog = h(
      "div",
      { class: "photo-dialog", role: "dialog", "aria-modal": "true", "aria-label": `Photo ${req.name}`, testid: "photo-view" },
      h("div", { class: "photo-head" }, h("strong", {}, req.name), req.title ? h("span", { class: "muted" }, ` ${req.title}`) : null, nav, h("button", { class: "icon", "aria-label": "Close", onclick: () => this.close() }, "×")),
      stage,
      info,
    );
    this.overlay = h("div", { class: "photo-overlay" }, dialog);
    this.overlay.addEventListener("click", (e) => e.target === this.overlay && this.close());
    this.host.append(this.overlay);
    void this.load(req, stage);
  }

  private async load(req: PhotoRequest, stage: HTMLElement): Promise<void> {
    const path = req.image?.url ?? `/v1/snapshots/${req.snapshotId}/images/${encodeURIComponent(req.name)}`;
    try {
      const res = await request(path);
      const blob = await res.blob();
      if (this.current !== req) return;
      this.url = URL.createObjectURL(blob);
      const img = h("img", { src: this.url, alt: req.name, class: "photo" });
      await img.decode().catch(() => undefined);
      const w = req.image?.width ?? img.naturalWidth;
      const hgt = req.image?.height ?? img.naturalHeight;
      const overlay = svg("svg", { viewBox: `0 0 ${w} ${hgt}`, class: "photo-overlay-svg", preserveAspectRatio: "none" });
      for (const d of req.image?.detections ?? []) {
        const [x0, y0, x1, y1] = d.box_px;
        const g = svg("g", { testid: "photo-box", "data-class": d.class_name });
        g.append(svg("rect", { x: x0, y: y0, width: x1 - x0, height: y1 - y0, class: "det-box" }));
        const label = svg("text", { x: x0 + 3, y: Math.max(y0 - 4, 12), class: "det-label" });
        label.textContent = `${d.class_name}${d.confidence !== null && d.confidence !== undefined ? ` ${d.confidence.toFixed(2)}` : ""}`;
        g.append(label);
        overlay.append(g);
      }
      if (req.view?.outline_px?.length) {
        const points = req.view.outline_px.map(([u, v]) => `${u},${v}`).join(" ");
        overlay.append(svg("polygon", { points, class: "outline", testid: "photo-outline", style: `stroke:${req.colour ?? "#f5a524"};fill:${req.colour ?? "#f5a524"}` }));
      }
      if (req.view?.box_px) {
        const [x0, y0, x1, y1] = req.view.box_px;
        overlay.append(svg("rect", { x: x0, y: y0, width: x1 - x0, height: y1 - y0, class: "outline-box", style: `stroke:${req.colour ?? "#f5a524"}` }));
      }
      const frame = h("div", { class: "photo-frame", style: `aspect-ratio:${w}/${hgt}` }, img);
      frame.append(overlay);
      stage.replaceChildren(frame);
    } catch (err) {
      if (this.current !== req) return;
      const e = err as ApiError;
      stage.replaceChildren(
        e.status === 410
          ? errorBanner("Photo deleted", `${e.detail} (the retention policy removed this snapshot's photos).`, e.code)
          : errorBanner("Could not load the photo", e.detail ?? String(err), e.code),
      );
    }
  }
}
