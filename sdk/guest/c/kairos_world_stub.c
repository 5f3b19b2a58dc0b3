/*
 * Link this file instead of wit-bindgen's `*_component_type.o` (the bindings here are
 * generated with --no-object-file). The generated code references one symbol per world to
 * force that object in; these empty definitions satisfy it. The world itself is attached
 * afterwards by `kairos plugin componentize`, from the WIT the server embeds, so no binary
 * object needs to be committed or kept in step with the WIT.
 */
__attribute__((weak)) void __component_type_object_force_link_horizon_policy(void) {}
__attribute__((weak)) void __component_type_object_force_link_priority_policy(void) {}
