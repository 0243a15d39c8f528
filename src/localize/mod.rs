//! Geometry and the hierarchical localizer.
