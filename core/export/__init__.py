"""Hand-offs to the tools that consume our lighting as it is: three.js, glTF, USD, Blender,
Unity, ARKit, VFX pipelines (EXR sequences). Pure functions over numpy/torch arrays; each
module owns one consumer's conventions and says where it took them from. The service and
the CLI only call these (docs/integrations.md)."""
