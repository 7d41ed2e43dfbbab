"""The paper's experiments (`reports`) and the demo (`demo`). They load `data_synth`, the
synthetic-scene generator, when they run; `import jaxrefl` does not."""
