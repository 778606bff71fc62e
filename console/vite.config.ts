import { defineConfig } from "vite";

// Served by the API at /ui/ (assets under /ui/assets/), same origin, no CDN.
export default defineConfig({
  base: "/ui/",
  build: {
    outDir: "dist",
    emptyOutDir: true,
    sourcemap: false,
    chunkSizeWarningLimit: 1500,
  },
  server: {
    proxy: { "/v1": "http://127.0.0.1:8000" },
  },
});
