"""The add-on's interface: the sidebar panels of the 3D Viewport, which draw the properties and call the
operators by name."""
