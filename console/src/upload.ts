// Upload a capture folder (images/, labels/, cameras.json) dropped on the box or chosen with
// the folder picker: one multipart POST with XMLHttpRequest upload progress, then the job.

import { authHeaders, type Job } from "./api";
import { append, errorBanner, h } from "./dom";

const IMAGE = /\.(jpe?g|png)$/i;

export interface CaptureFiles {
  images: File[];
  detections: File[];
  cameras: File | null;
  ignored: string[];
}

/** Sorts dropped files into the upload's fields by name: JPEG/PNG images, YOLO .txt
 * labels, cameras.json; anything else is listed as ignored. */
export function sortCapture(files: Array<{ file: File; path: string }>): CaptureFiles {
  const out: CaptureFiles = { images: [], detections: [], cameras: null, ignored: [] };
  for (const { file, path } of files) {
    const name = file.name;
    if (IMAGE.test(name)) out.images.push(file);
    else if (/\.txt$/i.test(name) && name.toLowerCase() !== "classes.txt") out.detections.push(file);
    else if (name === "cameras.json") out.cameras = file;
    else out.ignored.push(path);
  }
  out.images.sort((a, b) => a.name.localeCompare(b.name));
  out.detections.sort((a, b) => a.name.localeCompare(b.name));
  return out;
}

async function readEntry(entry: FileSystemEntry, path: string, out: Array<{ file: File; path: string }>): Promise<void> {
  if (entry.isFile) {
    const file = await new Promise<File>((resolve, reject) => (entry as FileSystemFileEntry).file(resolve, reject));
    out.push({ file, path: path + file.name });
  } else if (entry.isDirectory) {
    const reader = (entry as FileSystemDirectoryEntry).createReader();
    for (;;) {
      const batch = await new Promise<FileSystemEntry[]>((resolve, reject) => reader.readEntries(resolve, reject));
      if (batch.length === 0) break;
      for (const child of batch) await readEntry(child, `${path}${entry.name}/`, out);
    }
  }
}

export class UploadBox {
  readonly el: HTMLElement;
  private status = h("div", { class: "upload-status" });
  private busy = false;

  constructor(
    private readonly envId: string,
    private readonly onAccepted: (job: Job) => void,
  ) {
    const picker = h("input", { type: "file", multiple: true, webkitdirectory: true, class: "hidden-input", id: "upload-picker", testid: "upload-input" });
    picker.addEventListener("change", () => {
      const files = [...(picker.files ?? [])].map((file) => ({ file, path: file.webkitRelativePath || file.name }));
      picker.value = "";
      void this.send(files);
    });
    const drop = h(
      "div",
      { class: "drop", testid: "upload-drop", tabindex: 0, role: "button", "aria-label": "Drop a capture folder here or choose one" },
      h("strong", {}, "Drop a capture folder here"),
      h("span", { class: "muted" }, "images (JPEG/PNG), labels/*.txt (YOLO), cameras.json"),
      h("label", { for: "upload-picker", class: "button small" }, "Choose a folder…"),
      picker,
    );
    drop.addEventListener("dragover", (e) => {
      e.preventDefault();
      drop.classList.add("over");
    });
    drop.addEventListener("dragleave", () => drop.classList.remove("over"));
    drop.addEventListener("drop", (e) => {
      e.preventDefault();
      drop.classList.remove("over");
      void this.fromDrop(e.dataTransfer);
    });
    drop.addEventListener("keydown", (e) => e.key === "Enter" && picker.click());
    this.el = h("div", {}, drop, this.status);
  }

  private async fromDrop(data: DataTransfer | null): Promise<void> {
    if (!data) return;
    const out: Array<{ file: File; path: string }> = [];
    const entries = [...data.items].map((i) => i.webkitGetAsEntry?.()).filter((e): e is FileSystemEntry => !!e);
    if (entries.length) for (const e of entries) await readEntry(e, "", out);
    else for (const f of [...data.files]) out.push({ file: f, path: f.name });
    await this.send(out);
  }

  async send(files: Array<{ file: File; path: string }>): Promise<void> {
    if (this.busy) return;
    const capture = sortCapture(files);
    if (capture.images.length === 0) {
      this.status.replaceChildren(errorBanner("Nothing to upload", `No JPEG or PNG images among the ${files.length} files dropped.`));
      return;
    }
    const form = new FormData();
    for (const f of capture.images) form.append("images", f, f.name);
    for (const f of capture.detections) form.append("detections", f, f.name);
    if (capture.cameras) form.append("cameras", capture.cameras, "cameras.json");
    const fill = h("div", { class: "fill", style: "width:0%" });
    const label = h("span", { class: "muted" }, "starting…");
    const total = [...capture.images, ...capture.detections].reduce((n, f) => n + f.size, capture.cameras?.size ?? 0);
    this.status.replaceChildren();
    append(
      this.status,
      h("div", {}, `${capture.images.length} images, ${capture.detections.length} label files${capture.cameras ? ", cameras.json" : ""} · ${(total / 1e6).toFixed(1)} MB`),
      capture.ignored.length ? h("div", { class: "muted" }, `ignored: ${capture.ignored.slice(0, 5).join(", ")}${capture.ignored.length > 5 ? "…" : ""}`) : null,
      h("div", { class: "progress", testid: "upload-progress" }, h("div", { class: "bar" }, fill), label),
    );
    this.busy = true;
    const xhr = new XMLHttpRequest();
    xhr.open("POST", `/v1/environments/${this.envId}/snapshots`);
    for (const [k, v] of Object.entries(authHeaders())) xhr.setRequestHeader(k, v);
    xhr.setRequestHeader("Idempotency-Key", crypto.randomUUID());
    xhr.upload.onprogress = (e) => {
      if (!e.lengthComputable) return;
      const pct = Math.round((100 * e.loaded) / e.total);
      fill.style.width = `${pct}%`;
      label.textContent = `uploading ${pct}% (${(e.loaded / 1e6).toFixed(1)} / ${(e.total / 1e6).toFixed(1)} MB)`;
    };
    xhr.onerror = () => {
      this.busy = false;
      this.status.append(errorBanner("Upload failed", "The connection to the service was lost."));
    };
    xhr.onload = () => {
      this.busy = false;
      let body: { job?: Job; snapshot?: { seq: number }; error?: string; detail?: string } = {};
      try {
        body = JSON.parse(xhr.responseText);
      } catch {
        /* not JSON */
      }
      if (xhr.status === 202 && body.job) {
        fill.style.width = "100%";
        label.textContent = `uploaded: snapshot #${body.snapshot?.seq ?? "?"}, job ${body.job.state}`;
        this.onAccepted(body.job);
      } else {
        this.status.append(errorBanner(`Upload refused (${xhr.status})`, body.detail ?? xhr.statusText, body.error));
      }
    };
    xhr.send(form);
  }
}
