//! Looking at what was built: statistics and exports of shards ([`shards`]), the HTML report of a
//! corpus ([`report`]), and the contact sheets both draw ([`contact_sheet`]).

pub mod contact_sheet;
pub mod report;
pub mod shards;
