//! COLMAP models (binary and text) and database.db.
