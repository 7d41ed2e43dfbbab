"""Hardware: light selection (`select`), capture sessions (`session`), the serial rig driver
and its simulator. Imported on use (`import jaxrefl.capture.session`): `import jaxrefl` does
not load pyserial."""
