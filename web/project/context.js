// What every panel of the project page shares: the page state, the panels' cards and the pipeline's
// vocabulary. Panels re-render each other through ctx.render (never by importing each other).

/**
 * @typedef {Object} ProjectContext
 * @property {number} projectId
 * @property {Object} state      project, classes, runs, health, stream, compare selection, metrics cache …
 * @property {Object<string, HTMLElement>} els  one card per panel (head, run, runs, compare, classes, params)
 * @property {Object} pipeline   GET /pipeline: stages, form, labelers, run_statuses
 * @property {Map<string, Object>} stages  stage name → {label, description, per_frame}
 * @property {Set<string>} active    run states of a queued or working run
 * @property {Set<string>} terminal  run states of an ended run
 * @property {function(string, string=): void} toast
 * @property {Object<string, function(): (void|Promise<void>)>} render   head, run, runs, compare, classes, params
 * @property {Object<string, function>} actions  startRun, runAction, follow
 */

/** The context of one mounted project page. */
export function projectContext({ projectId, state, els, pipeline, toast }) {
  return {
    projectId,
    state,
    els,
    pipeline,
    stages: new Map(pipeline.stages.map((s) => [s.name, s])),
    active: new Set(pipeline.run_statuses.active),
    terminal: new Set(pipeline.run_statuses.terminal),
    toast,
    render: {},
    actions: {},
  };
}

export function latestRun(ctx) {
  return ctx.state.runs.length ? ctx.state.runs[0] : null;
}
