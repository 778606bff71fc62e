// One environment: the twin state table beside the 3D view, the timeline of snapshots and
// comparisons (live job progress), the change/object panel, photos, upload.

import type * as THREE from "three";
import { GLTFLoader } from "three/examples/jsm/loaders/GLTFLoader.js";
import {
  ApiError,
  FINAL_JOB_STATES,
  canCancel,
  canRerun,
  canUpload,
  getJson,
  postJson,
  request,
  type Change,
  type ChangeView,
  type ClusterPoints,
  type Comparison,
  type Environment,
  type History,
  type ImageInfo,
  type Instance,
  type Job,
  type KeyInfo,
  type LibraryObject,
  type Matrix4,
  type Snapshot,
  type TwinState,
} from "./api";
import { append, empty, errorBanner, fmtNum, fmtTime, h, loading, shortId } from "./dom";
import { PhotoView } from "./photo";
import { parsePly } from "./ply";
import { UploadBox } from "./upload";
import { CHANGE_COLOURS, Viewer, type Layer, type Pick } from "./viewer";

/** Points asked of the decimated cloud endpoint: what a browser draws smoothly. */
export const DEFAULT_MAX_POINTS = 300_000;
/** How often an environment page with no job running looks for new snapshots. */
const IDLE_REFRESH_MS = 10_000;

interface Focus {
  snapshot: Snapshot;
  comparison: Comparison | null;
  clusters: ClusterPoints[];
  images: ImageInfo[] | null;
}

function hashParams(): URLSearchParams {
  const q = location.hash.indexOf("?");
  return new URLSearchParams(q >= 0 ? location.hash.slice(q + 1) : "");
}

export class EnvironmentPage {
  private env: Environment | null = null;
  private snapshots: Snapshot[] = [];
  private comparisons: Comparison[] = [];
  private twin: TwinState | null = null;
  private library = new Map<string, LibraryObject>();
  private jobs = new Map<string, Job>();
  private focus: Focus | null = null;
  private viewer: Viewer | null = null;
  private models = new Map<string, Promise<THREE.Object3D | null>>();
  private pollTimer: number | null = null;
  private disposed = false;
  private selectedKey: string | null = null;
  private loadToken = 0;
  /** What the timeline last rendered, jobs' progress aside (see showJobs). */
  private timelineShown = "";

  private readonly titleEl = h("div", { class: "env-title" });
  private readonly bannerEl = h("div", { class: "banners" });
  private readonly twinEl = h("section", { class: "card twin" }, h("h2", {}, "Twin state"), loading("the twin"));
  private readonly timelineEl = h("section", { class: "card timeline", testid: "timeline" }, h("h2", {}, "Timeline"), loading("snapshots"));
  private readonly uploadEl = h("section", { class: "card upload" });
  private readonly viewStatus = h("div", { class: "view-status" });
  private readonly canvasBox = h("div", { class: "canvas-box" });
  private readonly panelEl = h("aside", { class: "panel", hidden: true });
  private readonly photo: PhotoView;
  private readonly toggles: Record<Layer, HTMLInputElement>;

  constructor(
    main: HTMLElement,
    private readonly envId: string,
    private readonly me: KeyInfo,
  ) {
    this.photo = new PhotoView(document.body);
    const layerNames: Array<[Layer, string, boolean]> = [
      ["before", "Before", false],
      ["after", "After", true],
      ["clusters", "Changes", true],
      ["models", "Models", true],
      ["ghosts", "Previous poses", true],
      ["cameras", "Cameras", true],
    ];
    this.toggles = {} as Record<Layer, HTMLInputElement>;
    const toolbar = h("div", { class: "toolbar", role: "toolbar" });
    for (const [layer, label, on] of layerNames) {
      const box = h("input", { type: "checkbox", "data-layer": layer });
      box.checked = on;
      box.addEventListener("change", () => this.setLayer(layer, box.checked));
      this.toggles[layer] = box;
      toolbar.append(h("label", { class: "toggle" }, box, label));
    }
    const legend = h(
      "div",
      { class: "legend" },
      ...["added", "removed", "moved", "swapped", "unidentified", "unchanged"].map((t) => h("span", {}, h("i", { style: `background:${CHANGE_COLOURS[t]}` }), t)),
      h("span", {}, h("i", { style: `background:${CHANGE_COLOURS.added};opacity:0.35` }), "cluster without a change"),
    );
    const viewCard = h("section", { class: "card view" }, h("div", { class: "view-head" }, h("h2", {}, "3D view"), toolbar), h("div", { class: "stage" }, this.canvasBox, this.panelEl, this.viewStatus), legend);
    const side = h("div", { class: "side" }, this.twinEl, this.timelineEl, this.uploadEl);
    main.append(h("div", { class: "env-head" }, h("a", { href: "#/environments", class: "back" }, "← Environments"), this.titleEl), this.bannerEl, h("div", { class: "layout" }, viewCard, side));
    try {
      this.viewer = new Viewer(this.canvasBox);
      this.viewer.onPick = (p) => this.onPick(p);
    } catch (err) {
      this.canvasBox.append(errorBanner("No 3D view", `WebGL is not available in this browser: ${String(err)}`));
    }
    this.renderUpload();
    void this.load();
  }

  dispose(): void {
    this.disposed = true;
    if (this.pollTimer !== null) clearTimeout(this.pollTimer);
    this.viewer?.dispose();
    this.photo.close();
  }

  // ---------------------------------------------------------------- data

  private async load(): Promise<void> {
    try {
      const [env, snapshots, comparisons, twin, objects] = await Promise.all([
        getJson<Environment>(`/v1/environments/${this.envId}`),
        getJson<Snapshot[]>(`/v1/environments/${this.envId}/snapshots`),
        getJson<Comparison[]>(`/v1/environments/${this.envId}/comparisons`),
        getJson<TwinState>(`/v1/environments/${this.envId}/state`),
        getJson<LibraryObject[]>(`/v1/objects`).catch(() => [] as LibraryObject[]),
      ]);
      if (this.disposed) return;
      this.env = env;
      this.snapshots = snapshots;
      this.comparisons = comparisons;
      this.twin = twin;
      for (const o of objects) if (o.state === "ready" || !this.library.has(o.name)) this.library.set(o.name, o);
      this.renderTitle();
      this.renderTwin();
      this.renderTimeline();
      await this.pollJobs();
      const wanted = hashParams().get("snapshot");
      const target = snapshots.find((s) => s.id === wanted) ?? this.defaultFocus();
      if (target) await this.setFocus(target);
      else this.viewStatus.replaceChildren(empty("No reconstructed snapshot yet: upload a capture to see the cloud."));
    } catch (err) {
      const e = err as ApiError;
      this.twinEl.replaceChildren(h("h2", {}, "Twin state"));
      this.timelineEl.replaceChildren(h("h2", {}, "Timeline"));
      this.bannerEl.replaceChildren(
        e.status === 404
          ? errorBanner("Environment not found", e.detail, e.code)
          : errorBanner("Could not load the environment", e.detail ?? String(err), e.code),
      );
    }
  }

  private async refresh(): Promise<void> {
    const [snapshots, comparisons, twin] = await Promise.all([
      getJson<Snapshot[]>(`/v1/environments/${this.envId}/snapshots`),
      getJson<Comparison[]>(`/v1/environments/${this.envId}/comparisons`),
      getJson<TwinState>(`/v1/environments/${this.envId}/state`),
    ]);
    if (this.disposed) return;
    const same = JSON.stringify([snapshots, comparisons, twin]) === JSON.stringify([this.snapshots, this.comparisons, this.twin]);
    if (same) return; // nothing new: leave the page as it is (rows, selection, scroll)
    const hadFocus = this.focus?.snapshot.id;
    this.snapshots = snapshots;
    this.comparisons = comparisons;
    this.twin = twin;
    this.renderTwin();
    this.renderTimeline();
    if (!hadFocus) {
      const target = this.defaultFocus();
      if (target) await this.setFocus(target);
    }
  }

  /** The newest reconstructed snapshot (it shows its comparison, when it has one). */
  private defaultFocus(): Snapshot | undefined {
    return this.snapshots.find((s) => s.state === "reconstructed");
  }

  private comparisonOf(snapshot: Snapshot): Comparison | null {
    return (
      this.comparisons.find((c) => c.id === snapshot.comparison) ??
      this.comparisons.find((c) => c.after === snapshot.id && c.state === "succeeded") ??
      null
    );
  }

  private seqOf(snapshotId: string | null | undefined): string {
    if (!snapshotId) return "—";
    const s = this.snapshots.find((x) => x.id === snapshotId);
    return s ? `#${s.seq}` : shortId(snapshotId);
  }

  // ---------------------------------------------------------------- jobs

  private activeJobIds(): string[] {
    const ids = new Set<string>();
    for (const s of this.snapshots) if (s.job && !["reconstructed", "failed", "cancelled", "deleted"].includes(s.state)) ids.add(s.job);
    for (const c of this.comparisons) if (c.job && !["succeeded", "failed", "cancelled"].includes(c.state)) ids.add(c.job);
    for (const [id, job] of this.jobs) if (!FINAL_JOB_STATES.has(job.state)) ids.add(id);
    return [...ids];
  }

  private async pollJobs(): Promise<void> {
    if (this.disposed) return;
    const ids = this.activeJobIds();
    // failed snapshots: fetch their jobs once for the error detail
    for (const s of this.snapshots) if (s.job && (s.state === "failed" || s.state === "cancelled") && !this.jobs.has(s.job)) ids.push(s.job);
    for (const c of this.comparisons) if (c.job && (c.state === "failed" || c.state === "cancelled") && !this.jobs.has(c.job)) ids.push(c.job);
    let finished = false;
    await Promise.all(
      ids.map(async (id) => {
        try {
          const before = this.jobs.get(id);
          const job = await getJson<Job>(`/v1/jobs/${id}`);
          this.jobs.set(id, job);
          if (before && !FINAL_JOB_STATES.has(before.state) && FINAL_JOB_STATES.has(job.state)) finished = true;
        } catch {
          /* the next poll tries again */
        }
      }),
    );
    if (this.disposed) return;
    if (finished) await this.refresh().catch(() => undefined);
    else this.showJobs();
    if (this.pollTimer !== null) clearTimeout(this.pollTimer);
    // jobs running: poll them; otherwise look for snapshots uploaded elsewhere now and then
    if (this.activeJobIds().length > 0) this.pollTimer = window.setTimeout(() => void this.pollJobs(), 1500);
    else this.pollTimer = window.setTimeout(() => void this.idleRefresh(), IDLE_REFRESH_MS);
  }

  /** The timeline's content apart from running jobs' progress and stage. */
  private timelineState(): string {
    const jobs = [...this.jobs.values()].map((j) => [j.id, j.state, j.cancel_requested, j.error?.code ?? null]);
    return JSON.stringify([this.snapshots, this.comparisons, jobs]);
  }

  /** After a poll: re-render the timeline only when more than a job's progress changed;
   * otherwise update the progress bars in place, so a button is never replaced under the
   * pointer (a click whose press and release land on two renders is lost). */
  private showJobs(): void {
    if (this.timelineState() !== this.timelineShown) return this.renderTimeline();
    for (const bar of this.timelineEl.querySelectorAll<HTMLElement>("[data-job]")) {
      const job = this.jobs.get(bar.dataset.job ?? "");
      if (job) bar.replaceWith(this.progress(job));
    }
  }

  private async idleRefresh(): Promise<void> {
    if (this.disposed) return;
    await this.refresh().catch(() => undefined);
    await this.pollJobs();
  }

  watchJob(job: Job): void {
    this.jobs.set(job.id, job);
    void this.refresh().then(() => this.pollJobs());
  }

  // ---------------------------------------------------------------- focus & 3D

  private async setFocus(snapshot: Snapshot): Promise<void> {
    const token = ++this.loadToken;
    const comparison = this.comparisonOf(snapshot);
    this.focus = { snapshot, comparison: comparison?.state === "succeeded" ? comparison : null, clusters: [], images: null };
    this.renderTimeline();
    this.renderTwin();
    const viewer = this.viewer;
    if (!viewer) return;
    for (const layer of Object.keys(viewer.layers) as Layer[]) viewer.clear(layer);
    viewer.requestRender();
    this.viewStatus.replaceChildren(loading(`the cloud of snapshot #${snapshot.seq}`));
    try {
      await this.loadCloud(snapshot.id, "after", token, true);
    } catch (err) {
      if (token !== this.loadToken) return;
      const e = err as ApiError;
      this.viewStatus.replaceChildren(errorBanner(`No cloud for snapshot #${snapshot.seq}`, e.detail ?? String(err), e.code));
      return;
    }
    if (token !== this.loadToken) return;
    if (this.toggles.before.checked && this.focus.comparison) void this.loadCloud(this.focus.comparison.before, "before", token, false).catch(() => undefined);
    await Promise.all([this.loadChanges(token), this.loadImages(token)]);
  }

  private async loadCloud(snapshotId: string, layer: "before" | "after", token: number, timed: boolean): Promise<void> {
    const params = hashParams();
    const full = params.get("full") === "1";
    const maxPoints = Number(params.get("points")) || DEFAULT_MAX_POINTS;
    const url = full ? `/v1/snapshots/${snapshotId}/pointcloud` : `/v1/snapshots/${snapshotId}/pointcloud?max_points=${maxPoints}`;
    const res = await request(url, { headers: { Accept: "application/octet-stream" } });
    const total = Number(res.headers.get("X-Total-Points")) || null;
    const cloud = parsePly(await res.arrayBuffer());
    if (token !== this.loadToken || !this.viewer) return;
    this.viewer.setCloud(layer, cloud);
    if (layer === "before") this.loadedBefore = snapshotId;
    if (timed) {
      const at = await this.viewer.drawn();
      performance.mark("twindelta-cloud-ready");
      window.__twindelta.cloudReadyMs = at;
      window.__twindelta.cloudPoints = cloud.count;
      window.__twindelta.cloudTotalPoints = total ?? cloud.count;
      window.__twindelta.cloudSource = full ? "full" : "decimated";
      this.viewStatus.replaceChildren(
        h("span", { class: "muted", testid: "cloud-status" }, `${cloud.count.toLocaleString()} points shown${total && total > cloud.count ? ` of ${total.toLocaleString()}` : ""} · ${Math.round(at)} ms`),
      );
    }
  }

  private loadedBefore: string | null = null;

  private setLayer(layer: Layer, on: boolean): void {
    this.viewer?.setVisible(layer, on);
    const cmp = this.focus?.comparison;
    if (layer === "before" && on && cmp && this.loadedBefore !== cmp.before) {
      void this.loadCloud(cmp.before, "before", this.loadToken, false).catch((err) => {
        const e = err as ApiError;
        this.viewStatus.replaceChildren(errorBanner("No 'before' cloud", e.detail ?? String(err), e.code));
      });
    }
  }

  private async loadChanges(token: number): Promise<void> {
    const viewer = this.viewer!;
    const cmp = this.focus?.comparison ?? null;
    const changes = cmp?.changes ?? [];
    if (cmp) {
      try {
        const body = await getJson<{ clusters: ClusterPoints[] }>(`/v1/comparisons/${cmp.id}/clusters`);
        if (token !== this.loadToken) return;
        this.focus!.clusters = body.clusters;
        viewer.setClusters(body.clusters, (id) => changes.find((c) => c.id === id)?.type ?? null);
      } catch (err) {
        const e = err as ApiError;
        this.viewStatus.append(errorBanner("No change clusters", e.detail ?? String(err), e.code));
      }
    }
    // changed objects at their poses (moved: the previous pose as a ghost; removed: the ghost only)
    const drawn = new Set<string>();
    const jobs: Promise<void>[] = [];
    for (const change of changes) {
      const objectId = this.objectIdOf(change.object, change.instance_id);
      const colour = CHANGE_COLOURS[change.type] ?? "#ffffff";
      const key = `change:${change.id}`;
      if (change.instance_id) drawn.add(change.instance_id);
      if (change.pose && change.type !== "removed") jobs.push(this.drawModel(objectId, change.pose, key, colour, false, token));
      if (change.previous_pose) jobs.push(this.drawModel(objectId, change.previous_pose, key, colour, true, token));
    }
    // the rest of the twin (when the view shows the snapshot the twin stands on)
    if (this.twin && this.focus && this.env && this.twin.objects.length <= 300 && (this.env.twin.snapshot === this.focus.snapshot.id || !cmp)) {
      for (const inst of this.twin.objects) {
        if (drawn.has(inst.instance_id) || !inst.pose) continue;
        jobs.push(this.drawModel(inst.object_id ?? this.objectIdOf(inst.object, null), inst.pose, `instance:${inst.instance_id}`, CHANGE_COLOURS.unchanged, false, token));
      }
    }
    await Promise.all(jobs);
  }

  private objectIdOf(name: string | null, instanceId: string | null): string | null {
    const inst = instanceId ? this.twin?.objects.find((o) => o.instance_id === instanceId) : undefined;
    if (inst?.object_id) return inst.object_id;
    return name ? (this.library.get(name)?.id ?? null) : null;
  }

  private model(objectId: string): Promise<THREE.Object3D | null> {
    let p = this.models.get(objectId);
    if (!p) {
      p = request(`/v1/objects/${objectId}/model`)
        .then((r) => r.arrayBuffer())
        .then((buf) => new GLTFLoader().parseAsync(buf, ""))
        // object frame, metres, +z up: env_from_object applies to it unchanged
        .then((gltf) => gltf.scene as THREE.Object3D)
        .catch(() => null);
      this.models.set(objectId, p);
    }
    return p;
  }

  private async drawModel(objectId: string | null, pose: Matrix4, key: string, colour: string, ghost: boolean, token: number): Promise<void> {
    const model = objectId ? await this.model(objectId) : null;
    if (token !== this.loadToken || !this.viewer) return;
    if (model) this.viewer.addModel(model, pose, key, colour, ghost);
    else if (!ghost) this.viewer.addMarker(pose, key, colour);
    window.__twindelta.modelsDrawn += 1;
    if (this.selectedKey === key) this.viewer.highlight(key);
  }

  private async loadImages(token: number): Promise<void> {
    const snapshot = this.focus!.snapshot;
    try {
      const images = await getJson<ImageInfo[]>(`/v1/snapshots/${snapshot.id}/images`);
      if (token !== this.loadToken) return;
      this.focus!.images = images;
      const box = this.viewer!.layers.after.children[0] as THREE.Points | undefined;
      const radius = box?.geometry.boundingSphere?.radius ?? 3;
      this.viewer!.setFrusta(images, Math.min(0.35, Math.max(0.08, radius * 0.04)));
    } catch {
      this.focus!.images = [];
    }
  }

  // ---------------------------------------------------------------- picking & panel

  private onPick(pick: Pick): void {
    if (pick.kind === "frustum") return void this.openPhoto(pick.image, null);
    this.select(pick.key, true);
  }

  private select(key: string, fromView = false): void {
    this.selectedKey = key;
    this.viewer?.highlight(key);
    if (!fromView) this.viewer?.focusOn(key);
    for (const row of this.twinEl.querySelectorAll<HTMLElement>("tr[data-key]")) row.classList.toggle("selected", row.dataset.key === key || row.dataset.change === key);
    const [kind, id] = key.split(/:(.*)/s);
    const cmp = this.focus?.comparison;
    if (kind === "change") {
      const change = cmp?.changes.find((c) => c.id === id);
      if (change && cmp) return this.renderChangePanel(change, cmp);
    }
    const inst = this.twin?.objects.find((o) => o.instance_id === id);
    if (inst) this.renderInstancePanel(inst);
  }

  private closePanel(): void {
    this.panelEl.hidden = true;
    this.panelEl.removeAttribute("data-testid");
    this.selectedKey = null;
    this.viewer?.highlight(null);
  }

  private panelShell(title: string, subtitle: string, colour: string): HTMLElement {
    this.panelEl.hidden = false;
    this.panelEl.dataset.testid = "change-panel";
    const body = h("div", { class: "panel-body" });
    this.panelEl.replaceChildren(
      h(
        "div",
        { class: "panel-head" },
        h("span", { class: "swatch", style: `background:${colour}` }),
        h("div", {}, h("strong", {}, title), h("div", { class: "muted" }, subtitle)),
        h("button", { class: "icon", "aria-label": "Close", onclick: () => this.closePanel() }, "×"),
      ),
      body,
    );
    return body;
  }

  private renderChangePanel(change: Change, cmp: Comparison): void {
    const colour = CHANGE_COLOURS[change.type] ?? "#fff";
    const body = this.panelShell(`${change.type}: ${change.object ?? "no library object"}`, `change ${shortId(change.id)} · comparison ${this.seqOf(cmp.before)} → ${this.seqOf(cmp.after)}`, colour);
    append(
      body,
      kv([
        ["Instance", change.instance_id ? shortId(change.instance_id) : "—"],
        ["External id", change.external_id ?? "—"],
        change.replaced_object ? ["Replaced", `${change.replaced_object} (${change.replaced_external_id ?? shortId(change.replaced_instance_id)})`] : null,
        ["Cluster", change.cluster ? `${change.cluster.side}, ${change.cluster.n_points.toLocaleString()} points` : "—"],
      ]),
      h("h3", {}, "Pose (env_from_object, m)"),
      change.pose ? poseMatrix(change.pose) : h("p", { class: "muted" }, "no pose"),
      change.previous_pose ? h("h3", {}, "Previous pose") : null,
      change.previous_pose ? poseMatrix(change.previous_pose, "previous-pose") : null,
      h("h3", {}, "Pose quality"),
      qualityTable(change.pose_quality),
      h("h3", {}, "Identification"),
      this.identificationTable(change, cmp),
    );
    const viewsBox = h("div", { class: "views" });
    body.append(h("div", { class: "row" }, h("button", { class: "primary small", testid: "views-button", onclick: () => void this.showViews(change, cmp, viewsBox) }, "Views"), h("span", { class: "muted" }, "photos that saw this change")), viewsBox);
    if (change.instance_id) void this.appendHistory(body, change.instance_id);
  }

  private renderInstancePanel(inst: Instance): void {
    const body = this.panelShell(inst.object, `instance ${shortId(inst.instance_id)}`, CHANGE_COLOURS.unchanged);
    append(
      body,
      kv([
        ["External id", inst.external_id ?? "—"],
        ["Created", this.seqOf(inst.created_snapshot)],
        ["Last change", this.seqOf(inst.since_snapshot)],
        ["Last seen", this.seqOf(lastSeen(inst))],
      ]),
      h("h3", {}, "Pose (env_from_object, m)"),
      inst.pose ? poseMatrix(inst.pose) : h("p", { class: "muted" }, "pose unknown"),
      h("h3", {}, "Pose quality"),
      qualityTable(inst.pose_quality),
    );
    void this.appendHistory(body, inst.instance_id);
  }

  private identificationTable(change: Change, cmp: Comparison): HTMLElement {
    const clusterId = (change.cluster as { id?: number } | null)?.id ?? this.focus?.clusters.find((c) => c.change_id === change.id)?.id;
    const row = cmp.clusters.find((c) => c.id === clusterId);
    const ident = change.identification ?? {};
    const summary = kv([
      ["Metric", fmtNum(ident.metric)],
      ["IoU", fmtNum(ident.iou)],
      ["Overlaps / occurrences", ident.overlaps !== undefined ? `${ident.overlaps} / ${ident.occurrences}` : "—"],
    ]);
    if (!row) return summary;
    const entries = Object.entries(row.metrics).sort((a, b) => b[1] - a[1]);
    const table = h("table", { class: "table compact", testid: "ident-table" }, h("thead", {}, h("tr", {}, h("th", {}, "Class"), h("th", { class: "num" }, "Metric"))));
    const tbody = h("tbody");
    for (const [cls, metric] of entries) tbody.append(h("tr", { class: cls === change.object ? "selected" : "" }, h("td", {}, cls), h("td", { class: "num" }, fmtNum(metric))));
    table.append(tbody);
    return h("div", {}, summary, table);
  }

  private async appendHistory(body: HTMLElement, instanceId: string): Promise<void> {
    const box = h("div", { class: "history" }, h("h3", {}, "History"), loading("history"));
    body.append(box);
    try {
      const history = await getJson<History>(`/v1/environments/${this.envId}/objects/${instanceId}/history`);
      box.lastChild?.remove();
      if (history.poses.length === 0) return void box.append(empty("No recorded poses."));
      const table = h("table", { class: "table compact", testid: "history-table" }, h("thead", {}, h("tr", {}, h("th", {}, "Snapshot"), h("th", {}, "Change"), h("th", {}, "Position (m)"), h("th", {}, "At"))));
      const tbody = h("tbody");
      for (const p of history.poses) tbody.append(h("tr", {}, h("td", {}, this.seqOf(p.snapshot)), h("td", {}, h("span", { class: `badge ${p.change_type}` }, p.change_type)), h("td", {}, p.pose ? position(p.pose) : "—"), h("td", {}, fmtTime(p.at))));
      table.append(tbody);
      box.append(table);
    } catch (err) {
      box.lastChild?.remove();
      const e = err as ApiError;
      box.append(errorBanner("No history", e.detail ?? String(err), e.code));
    }
  }

  private async showViews(change: Change, cmp: Comparison, box: HTMLElement): Promise<void> {
    box.replaceChildren(loading("views"));
    try {
      const views = await getJson<ChangeView[]>(`/v1/comparisons/${cmp.id}/changes/${change.id}/views`);
      if (views.length === 0) return void box.replaceChildren(empty("No photo saw this change."));
      const list = h("ul", { class: "view-list" });
      for (const v of views) {
        list.append(
          h(
            "li",
            {},
            h("button", { class: "link", testid: "view-item", onclick: () => this.openPhoto(v.image, { change, views, cmp }) }, v.image),
            h("span", { class: "muted" }, ` IoU ${fmtNum(v.iou, 2)}${v.counted ? "" : " · not counted"}`),
          ),
        );
      }
      box.replaceChildren(list);
    } catch (err) {
      const e = err as ApiError;
      box.replaceChildren(errorBanner("No views", e.detail ?? String(err), e.code));
    }
  }

  private openPhoto(name: string, context: { change: Change; views: ChangeView[]; cmp: Comparison } | null): void {
    const images = this.focus?.images ?? [];
    const snapshotId = context ? context.cmp.after : this.focus?.snapshot.id;
    const image = images.find((i) => i.name === name);
    const view = context?.views.find((v) => v.image === name) ?? null;
    this.photo.open({
      snapshotId: snapshotId ?? "",
      image: image ?? null,
      name,
      view,
      colour: context ? CHANGE_COLOURS[context.change.type] : null,
      title: context ? `${context.change.type} ${context.change.object ?? ""}` : null,
      siblings: context ? context.views.map((v) => v.image) : images.map((i) => i.name),
      onNavigate: (next) => this.openPhoto(next, context),
    });
  }

  // ---------------------------------------------------------------- rendering

  private renderTitle(): void {
    const env = this.env!;
    this.titleEl.replaceChildren(
      h("h1", {}, env.name),
      h("span", { class: `badge ${env.twin.status}` }, `twin ${env.twin.status}`),
      h("span", { class: "muted" }, `${env.twin.snapshot ? ` at ${this.seqOf(env.twin.snapshot)}` : " (no snapshot yet)"} · classes: ${env.classes.join(", ")}`),
    );
  }

  private renderTwin(): void {
    const twin = this.twin;
    const el = this.twinEl;
    el.replaceChildren(h("h2", {}, "Twin state", twin ? h("span", { class: "muted count" }, ` (${twin.objects.length})`) : null));
    if (!twin) return void el.append(loading("the twin"));
    if (twin.objects.length === 0) return void el.append(empty("The twin has no objects yet."));
    const changes = this.focus?.comparison?.changes ?? [];
    // the external id column only once the twin platform named an instance
    const external = twin.objects.some((o) => o.external_id);
    const table = h(
      "table",
      { class: "table", testid: "twin-table" },
      h("thead", {}, h("tr", {}, h("th", {}, "Object / instance"), external ? h("th", {}, "External id") : null, h("th", {}, "Position (m)"), h("th", {}, "Verified"), h("th", {}, "Last change"), h("th", {}, "Last seen"))),
    );
    const tbody = h("tbody");
    for (const inst of twin.objects) {
      const change = changes.find((c) => c.instance_id === inst.instance_id);
      const key = change ? `change:${change.id}` : `instance:${inst.instance_id}`;
      const verified = inst.pose_quality?.verified;
      const row = h(
        "tr",
        { testid: "twin-row", class: "clickable", tabindex: 0, "data-key": `instance:${inst.instance_id}`, "data-instance": inst.instance_id, "data-change": change ? key : null, "data-object": inst.object },
        h("td", {}, change ? h("span", { class: "dot", style: `background:${CHANGE_COLOURS[change.type]}` }) : null, inst.object, h("div", { class: "mono muted" }, shortId(inst.instance_id))),
        external ? h("td", {}, inst.external_id ?? "—") : null,
        h("td", { class: "mono" }, inst.pose ? position(inst.pose) : "—"),
        h("td", {}, verified === true ? h("span", { class: "ok" }, "✓ yes") : verified === false ? h("span", { class: "warn" }, "✗ no") : "—"),
        h("td", {}, change ? h("span", { class: `badge ${change.type}` }, change.type) : null, ` ${this.seqOf(inst.since_snapshot)}`),
        h("td", {}, "last_seen_snapshot" in inst && !inst.last_seen_snapshot ? h("span", { class: "warn" }, "not seen") : this.seqOf(lastSeen(inst))),
      );
      if (this.selectedKey === key) row.classList.add("selected");
      row.addEventListener("click", () => this.select(key));
      row.addEventListener("keydown", (e) => e.key === "Enter" && this.select(key));
      tbody.append(row);
    }
    table.append(tbody);
    el.append(h("div", { class: "scroll" }, table));
  }

  private renderTimeline(): void {
    const el = this.timelineEl;
    this.timelineShown = this.timelineState();
    el.replaceChildren(h("h2", {}, "Timeline"));
    if (this.snapshots.length === 0) return void el.append(empty("No snapshots yet."));
    const list = h("ol", { class: "snapshots" });
    for (const s of this.snapshots) {
      const job = s.job ? this.jobs.get(s.job) : undefined;
      const focused = this.focus?.snapshot.id === s.id;
      const q = s.quality ?? {};
      const correction = q.alignment_correction as { translation_m?: number; rotation_deg?: number; applied?: boolean } | undefined;
      const markers = Array.isArray(q.markers_used) ? (q.markers_used as unknown[]).length : null;
      const item = h(
        "li",
        { class: `snapshot${focused ? " focused" : ""}`, testid: "snapshot-item", "data-id": s.id },
        h(
          "div",
          { class: "snap-head" },
          h("strong", {}, `#${s.seq}`),
          h("span", { class: `badge ${s.state}` }, s.state),
          h("span", { class: "muted" }, `${fmtTime(s.created_at)} · ${s.source} · ${s.n_images} images`),
          s.state === "reconstructed" ? h("button", { class: "small", onclick: () => void this.setFocus(s), disabled: focused }, focused ? "shown" : "show") : null,
        ),
        job && !FINAL_JOB_STATES.has(job.state) ? this.progress(job) : null,
        job && !FINAL_JOB_STATES.has(job.state) && canCancel(this.me) && !job.cancel_requested
          ? h("button", { class: "small danger", testid: "cancel-job", onclick: () => void this.cancel(job) }, "Cancel job")
          : null,
        s.state === "failed" && job?.error ? errorBanner(`Job failed: ${job.error.code}`, job.error.detail ?? "") : null,
        s.state === "cancelled" ? h("div", { class: "muted" }, `Cancelled${job?.error?.detail ? `: ${job.error.detail}` : ""}.`) : null,
        s.state === "reconstructed"
          ? h(
              "div",
              { class: "quality" },
              metric("points", fmtNum(q.points)),
              metric("images", q.images_registered !== undefined ? `${q.images_registered}/${q.images_total ?? s.n_images}` : "—"),
              metric("markers", markers !== null ? String(markers) : "—"),
              metric("marker residual", q.marker_residual_m !== undefined ? `${fmtNum((q.marker_residual_m as number) * 1000, 2)} mm` : "—"),
              metric("alignment residual", q.alignment_residual_m !== undefined ? `${fmtNum((q.alignment_residual_m as number) * 1000, 2)} mm` : "—"),
              metric("correction", correction ? `${fmtNum((correction.translation_m ?? 0) * 1000, 2)} mm / ${fmtNum(correction.rotation_deg, 3)}°${correction.applied === false ? " (not applied)" : ""}` : "—"),
            )
          : null,
      );
      const cmps = this.comparisons.filter((c) => c.after === s.id);
      for (const c of cmps) item.append(this.comparisonItem(c));
      list.append(item);
    }
    el.append(list);
  }

  private comparisonItem(c: Comparison): HTMLElement {
    const job = this.jobs.get(c.job);
    const counts = new Map<string, number>();
    for (const ch of c.changes) counts.set(ch.type, (counts.get(ch.type) ?? 0) + 1);
    const running = !["succeeded", "failed", "cancelled"].includes(c.state);
    const focused = this.focus?.comparison?.id === c.id;
    const actions = h("span", { class: "actions" });
    if (c.state === "succeeded") actions.append(h("button", { class: "small", disabled: focused, onclick: () => void this.focusComparison(c) }, focused ? "shown" : "show"));
    if (running && job && canCancel(this.me) && !job.cancel_requested) actions.append(h("button", { class: "small danger", testid: "cancel-job", onclick: () => void this.cancel(job) }, "Cancel"));
    if (!running && canRerun(this.me)) actions.append(h("button", { class: "small", testid: "rerun-comparison", onclick: () => void this.rerun(c) }, "Re-run"));
    return h(
      "div",
      { class: `comparison${focused ? " focused" : ""}`, testid: "comparison-item", "data-id": c.id },
      h(
        "div",
        { class: "snap-head" },
        h("span", {}, `compare ${this.seqOf(c.before)} → ${this.seqOf(c.after)}`),
        h("span", { class: `badge ${c.state}` }, c.state),
        c.automatic ? null : h("span", { class: "muted" }, "re-run"),
        actions,
      ),
      c.state === "succeeded"
        ? h("div", { class: "chips" }, c.changes.length === 0 ? h("span", { class: "muted" }, "no changes") : null, ...[...counts].map(([t, n]) => h("span", { class: `badge ${t}` }, `${n} ${t}`)))
        : null,
      running && job ? this.progress(job) : null,
      c.state === "failed" && job?.error ? errorBanner(`Comparison failed: ${job.error.code}`, job.error.detail ?? "") : null,
      c.state === "cancelled" ? h("div", { class: "muted" }, `Cancelled${job?.error?.detail ? `: ${job.error.detail}` : ""}.`) : null,
    );
  }

  private async focusComparison(c: Comparison): Promise<void> {
    const after = this.snapshots.find((s) => s.id === c.after);
    if (!after) return;
    await this.setFocus(after);
    if (this.focus && this.focus.comparison?.id !== c.id) {
      this.focus.comparison = c;
      this.renderTimeline();
      this.renderTwin();
      await this.loadChanges(this.loadToken);
    }
  }

  private progress(job: Job): HTMLElement {
    const pct = Math.round(job.progress * 100);
    return h(
      "div",
      { class: "progress", testid: "job-progress", "data-job": job.id },
      h("div", { class: "bar" }, h("div", { class: "fill", style: `width:${pct}%` })),
      h("span", { class: "muted" }, `${job.state}${job.stage ? ` · ${job.stage}` : ""} · ${pct}%${job.cancel_requested ? " · cancelling" : ""}`),
    );
  }

  private async cancel(job: Job): Promise<void> {
    try {
      this.jobs.set(job.id, await postJson<Job>(`/v1/jobs/${job.id}/cancel`, {}));
      void this.pollJobs();
    } catch (err) {
      const e = err as ApiError;
      this.bannerEl.replaceChildren(errorBanner("Cancel refused", e.detail, e.code));
    }
  }

  private async rerun(c: Comparison): Promise<void> {
    try {
      // the same options again: the preset and overrides, not the values they resolved to
      const { resolved: _resolved, ...options } = c.options ?? {};
      const next = await postJson<Comparison>(`/v1/environments/${this.envId}/comparisons`, { before: c.before, after: c.after, options });
      this.bannerEl.replaceChildren();
      this.watchJob(await getJson<Job>(`/v1/jobs/${next.job}`));
    } catch (err) {
      const e = err as ApiError;
      this.bannerEl.replaceChildren(errorBanner("Re-run refused", e.detail, e.code));
    }
  }

  private renderUpload(): void {
    if (!canUpload(this.me)) {
      this.uploadEl.replaceChildren(
        h("h2", {}, "Upload a capture"),
        h("div", { class: "state forbidden", testid: "upload-forbidden" }, `Your key (${this.me.scopes.join(", ")}) may look but not upload: a capture or admin key is needed.`),
      );
      return;
    }
    this.uploadEl.replaceChildren(h("h2", {}, "Upload a capture"), new UploadBox(this.envId, (job) => this.watchJob(job)).el);
  }
}

// ---------------------------------------------------------------- small views

/** The newest snapshot whose inventory showed the instance (``last_seen_snapshot``, from
 * the twin's inventory); "—" where the state does not carry it. */
function lastSeen(inst: Instance): string | null {
  return (inst.last_seen_snapshot as string | null | undefined) ?? null;
}

function position(pose: Matrix4): string {
  return `${pose[0][3].toFixed(3)}, ${pose[1][3].toFixed(3)}, ${pose[2][3].toFixed(3)}`;
}

function metric(label: string, value: string): HTMLElement {
  return h("span", { class: "metric" }, h("span", { class: "label" }, label), h("span", { class: "value" }, value));
}

function kv(rows: Array<[string, string] | null>): HTMLElement {
  const dl = h("dl", { class: "kv" });
  for (const r of rows) if (r) dl.append(h("dt", {}, r[0]), h("dd", {}, r[1]));
  return dl;
}

function poseMatrix(pose: Matrix4, testid = "pose-matrix"): HTMLElement {
  const table = h("table", { class: "matrix", testid });
  for (const row of pose) table.append(h("tr", {}, ...row.map((v) => h("td", {}, v.toFixed(4)))));
  return table;
}

function qualityTable(q: Record<string, unknown> | null): HTMLElement {
  if (!q) return h("p", { class: "muted" }, "none (set by hand, or not estimated)");
  const rows: Array<[string, string]> = [];
  for (const [k, v] of Object.entries(q)) {
    if (k === "equivalent_poses") {
      rows.push([k, Array.isArray(v) ? `${v.length}` : String(v)]);
    } else if (v !== null && typeof v === "object" && !Array.isArray(v)) {
      rows.push([k, Object.entries(v as Record<string, unknown>).map(([a, b]) => `${a} ${typeof b === "number" ? fmtNum(b) : String(b)}`).join(", ")]);
    } else if (Array.isArray(v)) {
      rows.push([k, v.length ? v.join("; ") : "—"]);
    } else {
      rows.push([k, typeof v === "number" ? fmtNum(v, 4) : String(v)]);
    }
  }
  return kv(rows);
}
