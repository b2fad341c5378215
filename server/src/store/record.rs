//! Reading a result row of either backend: [`StoreRow`] is the few column reads the store's
//! decoders use, so each stored type is decoded by one function (beside its type) for SQLite and
//! PostgreSQL alike.

use sqlx::Row;

/// A result row of a backend, read by column name. Every store table keeps integers as 64-bit,
/// reals as double, text as text and bytes as blobs on both backends, so one decoder fits both.
pub(crate) trait StoreRow {
    fn int(&self, column: &str) -> i64;
    fn int_or_null(&self, column: &str) -> Option<i64>;
    fn real(&self, column: &str) -> f64;
    fn real_or_null(&self, column: &str) -> Option<f64>;
    fn text(&self, column: &str) -> String;
    fn text_or_null(&self, column: &str) -> Option<String>;
    fn flag(&self, column: &str) -> bool;
    fn bytes(&self, column: &str) -> Vec<u8>;
}

macro_rules! store_row {
    ($row:ty) => {
        impl StoreRow for $row {
            fn int(&self, column: &str) -> i64 {
                self.get(column)
            }
            fn int_or_null(&self, column: &str) -> Option<i64> {
                self.get(column)
            }
            fn real(&self, column: &str) -> f64 {
                self.get(column)
            }
            fn real_or_null(&self, column: &str) -> Option<f64> {
                self.get(column)
            }
            fn text(&self, column: &str) -> String {
                self.get(column)
            }
            fn text_or_null(&self, column: &str) -> Option<String> {
                self.get(column)
            }
            fn flag(&self, column: &str) -> bool {
                self.get(column)
            }
            fn bytes(&self, column: &str) -> Vec<u8> {
                self.get(column)
            }
        }
    };
}

store_row!(sqlx::sqlite::SqliteRow);
store_row!(sqlx::postgres::PgRow);
