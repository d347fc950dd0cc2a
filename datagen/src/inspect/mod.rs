//! Looking at what was built: statistics and exports of shards ([`shards`]), the HTML report of a
//! corpus ([`report`]), the contact sheets both draw ([`contact_sheet`]), and a sequence with its
//! pairs as a 4D recording for the Rerun viewer ([`view`]).

pub mod contact_sheet;
pub mod report;
pub mod shards;
pub mod view;
