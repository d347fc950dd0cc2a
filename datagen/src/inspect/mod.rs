//! Looking at what was built: statistics and exports of shards ([`shards`]), the HTML report of a
//! corpus ([`report`]) with the contact sheets of `foundation::contact_sheet`, and a sequence with its
//! pairs as a 4D recording for the Rerun viewer ([`view`]).

pub mod report;
pub mod shards;
pub mod view;
