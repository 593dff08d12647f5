// Converts a layout written by foxglove-sdk's `foxglove.layouts` (config/foxglove/*.json: a
// tree of {type: "split", direction, items: [{proportion, content}]} and {type: "panel"})
// into the LayoutData of Foxglove Studio 1.48 (`configById` + a binary react-mosaic tree),
// which is what Studio 1.48's layout storage holds. Only what our layouts use is converted
// (split containers, Plot and StateTransitions panels); anything else is an error.
//
// Options Studio 1.48 does not know (`lineStyle`, `lineInterpolation`, `yAxisLabel`) are
// dropped: its Plot draws every series as a solid line. They are reported as `dropped`.
// The legend goes to the plot's left (LEGEND_WIDTH px): Studio 1.48 draws a "top" legend one
// series a line in a fixed-height band (`sidebarDimension`), which leaves a short plot.
const LEGEND_WIDTH = 170;

const PANEL_TYPES = new Set(["Plot", "StateTransitions"]);

function panelConfig(panelType, config, title, dropped) {
  const paths = (config.paths ?? []).map((p) => {
    for (const key of Object.keys(p)) {
      if (!["value", "label", "timestampMethod", "enabled", "color"].includes(key)) {
        dropped.add(`${panelType}.paths[].${key}`);
      }
    }
    const out = { value: p.value, enabled: p.enabled ?? true, timestampMethod: p.timestampMethod ?? "receiveTime" };
    if (p.label !== undefined) out.label = p.label;
    if (p.color !== undefined) out.color = p.color;
    return out;
  });
  if (panelType === "StateTransitions") {
    return { paths, isSynced: config.isSynced ?? true, foxglovePanelTitle: title };
  }
  for (const key of Object.keys(config)) {
    if (!["paths", "showLegend", "legendDisplay", "isSynced", "minYValue", "maxYValue"].includes(key)) {
      dropped.add(`Plot.${key}`);
    }
  }
  return {
    paths,
    minYValue: config.minYValue,
    maxYValue: config.maxYValue,
    showLegend: config.showLegend ?? true,
    legendDisplay: config.legendDisplay === "top" ? "left" : config.legendDisplay ?? "left",
    showPlotValuesInLegend: false,
    showXAxisLabels: true,
    showYAxisLabels: true,
    isSynced: config.isSynced ?? true,
    xAxisVal: "timestamp",
    sidebarDimension: LEGEND_WIDTH,
    foxglovePanelTitle: title,
  };
}

/** Returns {data: LayoutData, dropped: string[]}. Panel ids are numbered, so the output is stable. */
export function convertLayout(sdkLayout) {
  if (sdkLayout?.version !== 1 || typeof sdkLayout.content !== "object") {
    throw new Error("not a foxglove.layouts layout (version 1 with a content tree)");
  }
  const configById = {};
  const dropped = new Set();
  let counter = 0;

  function node(content) {
    if (content.type === "panel") {
      if (!PANEL_TYPES.has(content.panelType)) {
        throw new Error(`panel type ${content.panelType} is not converted`);
      }
      counter += 1;
      const id = `${content.panelType}!glider${counter}`;
      configById[id] = panelConfig(content.panelType, content.config ?? {}, content.title, dropped);
      return id;
    }
    if (content.type === "split") {
      const items = content.items ?? [];
      if (items.length === 0) throw new Error("empty split container");
      if (!["row", "column"].includes(content.direction)) {
        throw new Error(`split direction ${content.direction}`);
      }
      return split(items, content.direction);
    }
    throw new Error(`layout node type ${content.type} is not converted`);
  }

  // react-mosaic nodes are binary: n items become item0 | (item1 | (...)), each split at the
  // share of its first item in the proportions that remain.
  function split(items, direction) {
    if (items.length === 1) return node(items[0].content);
    const weights = items.map((i) => i.proportion ?? 1);
    const total = weights.reduce((a, b) => a + b, 0);
    return {
      first: node(items[0].content),
      second: split(items.slice(1), direction),
      direction,
      splitPercentage: (100 * weights[0]) / total,
    };
  }

  const layout = node(sdkLayout.content);
  return {
    data: {
      configById,
      globalVariables: {},
      userNodes: {},
      playbackConfig: { speed: 1 },
      layout,
    },
    dropped: [...dropped].sort(),
  };
}
