// The web shell around @foxglove/studio-base 1.48's App, in the spirit of Studio's own
// packages/studio-web: an app configuration, a layout storage and the data sources. Plain
// JavaScript (React.createElement), so no bundler is needed: the package ships its webpack
// build (assets/index.js, UMD) and loads its own chunks and workers beside it.
//
// The layout storage is in memory, seeded with `layout.json` (build.mjs converts
// config/foxglove/glider-1.json to Studio 1.48's format) under the id `glider-1`; the page
// is opened with `?layoutId=glider-1`, so no import dialog and no IndexedDB state is needed.
/* global React, ReactDOM */
(function () {
  "use strict";
  const studio = window; // the UMD bundle's exports

  class MemoryAppConfiguration {
    constructor(values) {
      this.values = new Map(Object.entries(values));
      this.listeners = new Map();
    }
    get(key) {
      return this.values.get(key);
    }
    async set(key, value) {
      this.values.set(key, value);
      for (const cb of this.listeners.get(key) ?? []) cb(value);
    }
    addChangeListener(key, cb) {
      if (!this.listeners.has(key)) this.listeners.set(key, new Set());
      this.listeners.get(key).add(cb);
    }
    removeChangeListener(key, cb) {
      this.listeners.get(key)?.delete(cb);
    }
  }

  // ILayoutStorage: one store whatever the namespace (this app has no accounts).
  class MemoryLayoutStorage {
    constructor(layouts) {
      this.layouts = new Map(layouts.map((l) => [l.id, l]));
    }
    async list() {
      return [...this.layouts.values()];
    }
    async get(_namespace, id) {
      return this.layouts.get(id);
    }
    async put(_namespace, layout) {
      this.layouts.set(layout.id, layout);
      return layout;
    }
    async delete(_namespace, id) {
      this.layouts.delete(id);
    }
    async importLayouts() {}
  }

  async function main() {
    const layout = await (await fetch("layout.json")).json();
    studio.overwriteFetch();
    await studio.waitForFonts();
    await studio.initI18n();
    const appConfiguration = new MemoryAppConfiguration({
      [studio.AppSetting.COLOR_SCHEME]: "light",
      [studio.AppSetting.TELEMETRY_ENABLED]: false,
      [studio.AppSetting.CRASH_REPORTING_ENABLED]: false,
      [studio.AppSetting.UPDATES_ENABLED]: false,
      [studio.AppSetting.HIDE_SIGN_IN_PROMPT]: true,
      [studio.AppSetting.SHOW_OPEN_DIALOG_ON_STARTUP]: false,
      [studio.AppSetting.TIMEZONE]: "UTC",
    });
    const layoutStorage = new MemoryLayoutStorage([
      {
        id: "glider-1",
        name: "glider-1",
        permission: "CREATOR_WRITE",
        baseline: { data: layout, savedAt: new Date(0).toISOString() },
        working: undefined,
        syncInfo: undefined,
      },
    ]);
    const dataSources = [
      new studio.McapLocalDataSourceFactory(),
      new studio.RemoteDataSourceFactory(),
      new studio.FoxgloveWebSocketDataSourceFactory(),
    ];
    ReactDOM.render(
      React.createElement(studio.App, {
        deepLinks: [window.location.href],
        dataSources,
        appConfiguration,
        layoutStorage,
        extensionLoaders: [],
        enableGlobalCss: true,
      }),
      document.getElementById("root"),
    );
    console.debug("App rendered");
  }

  main().catch((err) => {
    console.error("glider-hil studio shell failed:", err);
    document.getElementById("root").textContent = String(err);
  });
})();
